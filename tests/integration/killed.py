"""The real headless client in a thread, with the moments a kill-a-server test waits for."""

from __future__ import annotations

import threading

from client.app import run_client


class ClientUnderKill:
    """``run_client`` on ``url`` (scene demo, 50 ms target, redialling for 10 s) in a thread.

    mid : set once it has drawn its third selection (time to kill)
    moved : set once it has drawn two selections past ``kill_seq`` (the test sets it when it kills)
    """

    def __init__(self, url: str, duration: float, viewport) -> None:
        self.mid, self.moved = threading.Event(), threading.Event()
        self.kill_seq: int | None = None
        self._result: dict = {}
        self._thread = threading.Thread(target=lambda: self._result.update(run=run_client(
            url, "demo", duration=duration, viewport=viewport, target_frame_time=0.05, on_frame=self._on_frame,
            reconnect_timeout=10.0)))
        self._thread.start()

    def _on_frame(self, rec) -> None:
        if rec.seq >= 3:
            self.mid.set()
        if self.kill_seq is not None and rec.seq > self.kill_seq + 1:
            self.moved.set()

    def join(self, timeout: float):
        """The client's ``ClientRun`` once it has ended."""
        self._thread.join(timeout)
        return self._result["run"]
