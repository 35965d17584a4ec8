"""The other worker processes of a replica, for the admin endpoints that must see all its sessions.

The kernel spreads connections over a replica's workers (SO_REUSEPORT), so an
administrator's ``GET /sessions`` lands on one of them. Each worker also listens
on a private loopback port and writes it to a file named by its pid in a folder
the workers share; a worker asked for the replica's sessions answers with its
own and those its live peers give for ``?local=1``. A peer that died (its pid is
gone) or does not answer in time is left out.
"""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

__all__ = ["Peers"]


class Peers:
    """folder : shared by the replica's workers; me : this worker's pid"""

    def __init__(self, folder: str | os.PathLike[str], me: int | None = None, timeout: float = 2.0) -> None:
        self.folder = Path(folder)
        self.me = os.getpid() if me is None else int(me)
        self.timeout = float(timeout)

    def register(self, port: int) -> None:
        """Say where this worker's private port is (atomically: a peer never reads half a file)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = self.folder / f".{self.me}.tmp"
        tmp.write_text(str(int(port)))
        tmp.replace(self.folder / str(self.me))

    def others(self) -> list[tuple[int, int]]:
        """(pid, port) of every other live worker."""
        out = []
        for path in self.folder.glob("[0-9]*"):
            try:
                pid, port = int(path.name), int(path.read_text())
            except (OSError, ValueError):
                continue
            if pid != self.me and _alive(pid):
                out.append((pid, port))
        return sorted(out)

    async def ask(self, method: str, path: str, headers: dict) -> list[tuple[int, object]]:
        """Each live peer's answer to ``method path?local=1`` as (status, JSON body); the unreachable left out."""
        import httpx

        peers = self.others()
        if not peers:
            return []
        async with httpx.AsyncClient(timeout=self.timeout) as http:
            async def one(port: int):
                try:
                    r = await http.request(method, f"http://127.0.0.1:{port}{path}", params={"local": "1"},
                                           headers=headers)
                    return r.status_code, r.json()
                except Exception:  # gone or stuck: the replica's answer is what the others say
                    return None

            answers = await asyncio.gather(*(one(port) for _, port in peers))
        return [a for a in answers if a is not None]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
