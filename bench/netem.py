"""A bad network on loopback: latency, jitter, loss and cuts for the fault tests.

The fault tests want ``tc netem`` inside a network namespace the test creates. A
kernel can have network namespaces but no ``sch_netem`` module (``tc qdisc add ...
netem`` fails with "qdisc kind unknown"), as container and CI kernels often do, so
``DelayProxy`` stands in for it: a TCP relay on loopback that delays every
chunk it relays and emulates loss the way TCP shows it to an application — a lost
segment arrives late, after a retransmission timeout, and holds back everything
behind it. ``netem_available()`` says whether the real thing would work here;
the netem branch itself (a namespace with a veth pair and a netem qdisc around
the cluster) is not implemented, so the tests use the proxy either way.

What the proxy does not emulate: bandwidth limits, reordering (TCP hides it),
and loss at segment granularity — loss is drawn per relayed chunk (one ``read``
of up to ``chunk`` bytes), and a lost chunk costs a full RTO where real TCP often
recovers in one round trip by fast retransmit. Both make it harsher, not kinder.
"""

from __future__ import annotations

import asyncio
import functools
import os
import random
import socket
import struct
import subprocess
import threading
from dataclasses import dataclass, field

__all__ = ["netem_available", "Link", "DelayProxy"]


@functools.cache
def netem_available() -> bool:
    """True if a throw-away network namespace can get a ``netem`` qdisc (needs root and ``sch_netem``)."""
    name = f"walkstream-probe-{os.getpid()}"

    def run(*cmd: str) -> bool:
        try:
            return subprocess.run(cmd, capture_output=True, timeout=10).returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            return False

    if not run("ip", "netns", "add", name):
        return False
    try:
        return run("ip", "netns", "exec", name, "tc", "qdisc", "add", "dev", "lo", "root", "netem", "delay", "1ms")
    finally:
        run("ip", "netns", "del", name)


@dataclass
class Link:
    """One direction of a link: when a chunk that arrived at ``now`` is delivered.

    Pure and clock-free (the proxy passes the time in), so its invariants can be
    tested without sockets: delivery never goes back in time (TCP keeps order),
    each chunk takes at least ``latency - jitter``, and a lost chunk is delivered
    ``rto`` after it would have been, holding back the chunks behind it.
    """

    latency: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0
    rto: float = 0.2
    seed: int | None = None
    last: float = float("-inf")
    lost: int = 0
    _rng: random.Random = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.latency < 0 or self.jitter < 0 or self.rto < 0:
            raise ValueError("latency, jitter and rto must be non-negative")
        if self.jitter > self.latency:
            raise ValueError(f"jitter ({self.jitter}) larger than latency ({self.latency}) would deliver before sending")
        if not 0.0 <= self.loss <= 1.0:
            raise ValueError(f"loss is a probability, got {self.loss}")
        self._rng = random.Random(self.seed)

    def deliver_at(self, now: float) -> float:
        delay = self.latency + (self._rng.uniform(-self.jitter, self.jitter) if self.jitter else 0.0)
        if self.loss and self._rng.random() < self.loss:
            delay += self.rto
            self.lost += 1
        self.last = max(self.last, now + delay)
        return self.last


def _reset(writer: asyncio.StreamWriter) -> None:
    """Close a connection with a TCP reset, as a vanished network path or a dead peer leaves it."""
    sock = writer.get_extra_info("socket")
    if sock is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        except OSError:
            pass
    writer.transport.abort()


class DelayProxy:
    """A TCP relay from ``127.0.0.1:port`` to ``(host, target_port)`` that delays, loses and cuts.

    Every chunk read from one side is written to the other ``latency ± jitter``
    seconds later (one way; order kept); with probability ``loss`` a chunk is
    "lost" and arrives ``rto`` later, delaying all behind it. ``cut()`` resets
    every relayed connection (both sides) and resets new ones until ``restore()``.
    Runs an asyncio loop in its own thread; a context manager.

    For tests: ``port``, ``connections`` (open now), ``accepted``, ``refused``
    (reset while cut), ``bytes_up`` (client → target), ``bytes_down``, ``lost`` (chunks).
    """

    #: Chunks in flight per direction before the proxy stops reading (a TCP window's worth of backpressure).
    WINDOW = 64

    def __init__(self, host: str, target_port: int, *, latency: float = 0.0, jitter: float = 0.0,
                 loss: float = 0.0, rto: float = 0.2, seed: int | None = None, chunk: int = 65536):
        Link(latency, jitter, loss, rto)  # validate here, in the caller's thread
        self.host, self.target_port = host, target_port
        self.latency, self.jitter, self.loss, self.rto = latency, jitter, loss, rto
        self.chunk = chunk
        self._rng = random.Random(seed)
        self.accepted = 0
        self.refused = 0
        self.bytes_up = 0
        self.bytes_down = 0
        self._links: list[Link] = []
        self._conns: set[tuple[asyncio.StreamWriter, asyncio.StreamWriter]] = set()
        self._tasks: set[asyncio.Task] = set()
        self._cut = False
        self._changed = threading.Condition()
        self._loop = asyncio.new_event_loop()
        started = threading.Event()
        failure: list[BaseException] = []

        def main() -> None:
            asyncio.set_event_loop(self._loop)
            try:
                self._server = self._loop.run_until_complete(
                    asyncio.start_server(self._accept, "127.0.0.1", 0))
            except BaseException as exc:  # noqa: BLE001 - handed to the constructor's thread
                failure.append(exc)
                started.set()
                return
            started.set()
            self._loop.run_forever()

        self._thread = threading.Thread(target=main, name="DelayProxy", daemon=True)
        self._thread.start()
        started.wait()
        if failure:
            raise RuntimeError(f"the delay proxy could not listen: {failure[0]}") from failure[0]
        self.port: int = self._server.sockets[0].getsockname()[1]

    # -- what tests look at ---------------------------------------------------------------------

    def wait_for(self, predicate, timeout: float) -> bool:
        """Block until ``predicate(self)`` holds (checked whenever a connection is accepted, refused or ends)."""
        with self._changed:
            return self._changed.wait_for(lambda: predicate(self), timeout)

    def _notify(self) -> None:
        with self._changed:
            self._changed.notify_all()

    @property
    def connections(self) -> int:
        return len(self._conns)

    @property
    def lost(self) -> int:
        return sum(link.lost for link in list(self._links))

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    # -- faults ---------------------------------------------------------------------------------

    def _call(self, fn, timeout: float = 10.0):
        async def run():
            return fn()

        return asyncio.run_coroutine_threadsafe(run(), self._loop).result(timeout)

    def cut(self) -> int:
        """Reset every relayed connection, both sides, and every new one until ``restore()``; how many were cut."""
        def do() -> int:
            self._cut = True
            conns = list(self._conns)
            for client, upstream in conns:
                _reset(client)
                _reset(upstream)
            self._conns.clear()
            self._notify()
            return len(conns)

        return self._call(do)

    def restore(self) -> None:
        """Accept and relay connections again."""
        def do() -> None:
            self._cut = False

        self._call(do)

    # -- relaying -------------------------------------------------------------------------------

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        me = asyncio.current_task()
        self._tasks.add(me)
        try:
            await self._relay(reader, writer)
        except asyncio.CancelledError:
            pass  # closing: end quietly (asyncio's stream callback would log a cancelled handler as an error)
        finally:
            self._tasks.discard(me)

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._cut:
            self.refused += 1
            _reset(writer)
            self._notify()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection(self.host, self.target_port)
        except OSError:
            _reset(writer)
            return
        for w in (writer, up_writer):
            sock = w.get_extra_info("socket")
            if sock is not None:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if self._cut:  # cut while we connected
            _reset(writer)
            _reset(up_writer)
            return
        self.accepted += 1
        pair = (writer, up_writer)
        self._conns.add(pair)
        self._notify()
        seed = self._rng.getrandbits(32)
        links = [Link(self.latency, self.jitter, self.loss, self.rto, seed), Link(self.latency, self.jitter, self.loss, self.rto, seed + 1)]
        self._links += links
        pumps = [asyncio.create_task(self._pump(reader, up_writer, links[0], "bytes_up", pair)),
                 asyncio.create_task(self._pump(up_reader, writer, links[1], "bytes_down", pair))]
        self._tasks.update(pumps)
        try:
            await asyncio.gather(*pumps, return_exceptions=True)
        finally:
            for t in pumps:
                self._tasks.discard(t)
            self._conns.discard(pair)
            for w in pair:
                if not w.transport.is_closing():
                    w.close()
            self._notify()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, link: Link, counter: str,
                    pair: tuple) -> None:
        """Read chunks as they come; a second task writes each at its delivery time, in order.

        The queue is bounded (``WINDOW`` chunks), so a slow receiver slows the sender as
        TCP's window would, and the server still sees backpressure through the proxy.
        """
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue = asyncio.Queue(maxsize=self.WINDOW)

        async def deliver() -> None:
            try:
                while True:
                    at, data = await queue.get()
                    if data is None:
                        if writer.can_write_eof() and not writer.transport.is_closing():
                            writer.write_eof()
                        return
                    wait = at - loop.time()
                    if wait > 0:
                        await asyncio.sleep(wait)
                    setattr(self, counter, getattr(self, counter) + len(data))  # before the peer can see them
                    writer.write(data)
                    await writer.drain()
            except (ConnectionError, OSError):
                for w in pair:  # the far side is gone: so is the whole relayed connection
                    _reset(w)
                while (await queue.get())[1] is not None:  # let the reader run on to its end of file
                    pass

        sender = asyncio.create_task(deliver())
        try:
            while True:
                try:
                    data = await reader.read(self.chunk)
                except (ConnectionError, OSError):
                    data = b""
                await queue.put((link.deliver_at(loop.time()), data or None))
                if not data:
                    break
            await sender
        finally:
            if not sender.done():
                sender.cancel()

    # -- lifetime -------------------------------------------------------------------------------

    def close(self) -> None:
        if not self._loop.is_running():
            return

        async def stop() -> None:
            self._server.close()
            for client, upstream in list(self._conns):
                _reset(client)
                _reset(upstream)
            tasks = [t for t in self._tasks if t is not asyncio.current_task()]
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)  # let each unwind before the loop stops

        asyncio.run_coroutine_threadsafe(stop(), self._loop).result(10)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)

    def __enter__(self) -> "DelayProxy":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
