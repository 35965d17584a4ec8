"""Starting a replica: the listening socket, the scene stores, the state store's reachability.

Each refuses with ``ServeError`` naming the value at fault, so ``walkstream serve``
can say it in one line before it has loaded or warmed anything it need not.
"""

from __future__ import annotations

import errno
import socket
from pathlib import Path

from .scene.store import SceneStore

__all__ = ["ServeError", "load_scenes", "check_state_url", "bind_listener", "reserve_port"]


class ServeError(RuntimeError):
    """The server cannot start as asked (e.g. its state store is unreachable)."""


def load_scenes(paths: list[Path]) -> dict[str, SceneStore]:
    """Open scene stores by path; each is served under the name recorded in it."""
    scenes: dict[str, SceneStore] = {}
    where: dict[str, Path] = {}
    for path in paths:
        store = SceneStore.open(path)
        name = store.index.name
        if name in scenes:
            store.close()
            for s in scenes.values():
                s.close()
            raise ValueError(f"two stores name their scene {name!r}: {where[name]} and {path}")
        scenes[name], where[name] = store, Path(path)
    return scenes


def check_state_url(url: str, timeout: float = 3.0) -> None:
    """Refuse to start when the Redis at ``url`` does not answer (a clear error beats failing every resume)."""
    import redis

    from .state import _redact

    client = redis.Redis.from_url(url, socket_connect_timeout=timeout, socket_timeout=timeout)
    try:
        client.ping()
    except Exception as exc:
        raise ServeError(f"the Redis state store at {_redact(url)} is unreachable: {exc}") from None
    finally:
        client.close()


def bind_listener(host: str, port: int, send_buffer: int | None = None, *, reuse_port: bool = False,
                  listen: bool = True) -> socket.socket:
    """A listening TCP socket on ``host:port``; ``ServeError`` naming the address if it cannot be had.

    ``reuse_port``: one of several sockets on the port (SO_REUSEPORT), among which the kernel spreads new
    connections — a replica's worker processes each listen on their own. ``listen=False`` only binds: a
    bound socket that does not listen is given no connections, and holds the port for the workers."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if reuse_port:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        if send_buffer is not None:  # accepted connections inherit it (and lose autotuning)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, send_buffer)
        sock.bind((host, port))
        if listen:
            sock.listen(1024 if reuse_port else 128)  # connections queue in the backlog until uvicorn accepts them
    except (OSError, UnicodeError) as exc:
        sock.close()
        why = "the port is in use" if getattr(exc, "errno", None) == errno.EADDRINUSE else str(exc)
        raise ServeError(f"cannot listen on {host}:{port}: {why}") from None
    except OverflowError:
        sock.close()
        raise ServeError(f"cannot listen on {host}:{port}: the port must lie in 0..65535") from None
    return sock


def reserve_port(host: str, port: int) -> socket.socket:
    """The port for a replica's workers: checked free (a plain bind fails where anything listens, another
    replica's workers too), then held by a bound, non-listening SO_REUSEPORT socket the workers join."""
    probe = bind_listener(host, port, listen=False)
    bound = probe.getsockname()[1]
    probe.close()
    return bind_listener(host, bound, reuse_port=True, listen=False)
