"""A user-space network emulator: a UDP proxy on loopback that shapes both directions.

The kernel's netem is not available here (NOTES.md), so viewers reach the relay
through this proxy instead: ``NetworkEmulator(listen=("localhost", 0),
upstream=("127.0.0.1", relay_port), schedule=resolve("wifi"))``; viewers connect
to ``emulator.port``. Each client address gets its own upstream socket, so the
relay sees distinct clients and its replies find their way back; a mapping idle
for ``idle_timeout_s`` is closed. All clients share one emulated link (one home
line), shaped by ``server/net/shaper.py``.

Packets wait on a heap of departure times and a single ``call_at`` timer sends
the due ones; ``stats()["release_late_ms"]`` says how late they really left
(asyncio's epoll timeout has 1 ms steps, so the timer aims half of that early).

``listen`` host ``localhost`` binds both 127.0.0.1 and ::1 on one port, because
Chromium resolves ``localhost`` to ::1 and Python clients use 127.0.0.1. Only
loopback addresses are accepted: this is a test tool, not a router.

``tcp_passthrough=True`` also forwards TCP on the same port, unshaped, for what
@moq/watch fetches over HTTP from the relay's port (``/certificate.sha256``).

``EmulatorThread`` runs one in its own event loop on a daemon thread, for callers
without a loop (benchmarks driving Playwright's sync API).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import heapq
import ipaddress
import logging
import selectors
import socket
import statistics
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, TypeVar

from server.net.link_profile import Schedule
from server.net.profiles import resolve
from server.net.shaper import Fate, LinkShaper

log = logging.getLogger(__name__)

Address = tuple[str, int]
T = TypeVar("T")

_MAX_DATAGRAM = 65535
_READ_BATCH = 256  # datagrams read per wake-up, so one busy socket cannot starve the timer
_SOCKET_BUFFER = 4 << 20  # the kernel caps it at rmem_max/wmem_max; bursts need room
_EARLY_S = 0.0005  # the loop waits in whole ms (rounded up): aim half a step early


def emulator_loop() -> asyncio.AbstractEventLoop:
    """The event loop the emulator's timing is right on: a poll(2) selector. asyncio's
    default epoll selector rounds a wait up to whole milliseconds and hands epoll the
    result as a float, which epoll rounds up again: 9 ms becomes 9.000000000000002 and
    then 10 (for 22 of the first 200 whole ms). Every such release left a millisecond
    late: round trips through a 40 ms link measured 42.1-42.3 ms. PollSelector passes
    poll(2) the whole milliseconds as an integer; the emulator has few sockets, so
    poll's per-call scan costs nothing here."""
    poll_selector = getattr(selectors, "PollSelector", None)
    if poll_selector is None:  # not on this platform: asyncio's default
        return asyncio.new_event_loop()
    return asyncio.SelectorEventLoop(poll_selector())


_LATENESS_SAMPLES = 20000
_NO_IPV6 = (errno.EADDRNOTAVAIL, errno.EAFNOSUPPORT)
# The kernel stamps each datagram on arrival (Linux's SO_TIMESTAMPNS, which Python's
# socket module does not name): a packet read late by a busy loop still gets its delay
# counted from when it really arrived. Elsewhere the read time stands in.
_SO_TIMESTAMPNS = 35 if sys.platform == "linux" else None
_TIMESPEC = struct.Struct("@qq")
_ANCILLARY_SPACE = socket.CMSG_SPACE(_TIMESPEC.size)


class NonLoopbackError(ValueError):
    """An address that is not loopback (the emulator never touches a real network)."""


def loopback_hosts(host: str, role: str) -> list[str]:
    """The loopback IP addresses ``host`` stands for, or NonLoopbackError naming ``role``."""
    if host == "localhost":
        return ["127.0.0.1", "::1"]
    try:
        ip = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        raise NonLoopbackError(
            f"{role} host {host!r} is not an IP address: use 127.0.0.1, ::1 or localhost"
        ) from None
    if not ip.is_loopback:
        hint = " ('localhost' listens on both 127.0.0.1 and ::1)" if ip.is_unspecified else ""
        raise NonLoopbackError(
            f"{role} address {host} is not loopback: the network emulator only works "
            f"between loopback addresses (127.0.0.0/8, ::1){hint}"
        )
    return [str(ip)]


def _family(host: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def _udp_socket(family: socket.AddressFamily) -> socket.socket:
    sock = socket.socket(family, socket.SOCK_DGRAM)
    sock.setblocking(False)
    for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, option, _SOCKET_BUFFER)
    if _SO_TIMESTAMPNS is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
    return sock


def _bound_udp_socket(host: str, port: int) -> socket.socket:
    sock = _udp_socket(_family(host))
    try:
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    return sock


def _arrival(ancillary: list[tuple[int, int, bytes]], wall_minus_loop: float, now: float) -> float:
    """The kernel's arrival stamp on the loop's clock, or ``now`` without one."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            seconds, nanoseconds = _TIMESPEC.unpack_from(data)
            stamped = float(seconds) + float(nanoseconds) * 1e-9 - wall_minus_loop
            return min(now, stamped)  # never later than now: the wall clock may have stepped
    return now


@dataclass(eq=False)
class _Client:
    key: tuple[int, Any]
    listener: socket.socket
    address: Any  # as recvfrom gave it (a 4-tuple on IPv6)
    upstream: socket.socket
    last_seen: float


@dataclass(order=True)
class _Pending:
    depart_at: float
    seq: int
    sock: socket.socket = field(compare=False)
    data: bytes = field(compare=False)
    to: Any = field(compare=False)  # None: the socket is connected (upstream)


class NetworkEmulator:
    """A shaped UDP proxy from ``listen`` (loopback) to ``upstream`` (loopback)."""

    def __init__(
        self,
        listen: Address = ("localhost", 0),
        upstream: Address = ("127.0.0.1", 4443),
        schedule: Schedule | str = "lan",
        seed: int = 0,
        *,
        idle_timeout_s: float = 30.0,
        tcp_passthrough: bool = False,
    ) -> None:
        self._listen_hosts = loopback_hosts(listen[0], "listen")
        self._listen_port = listen[1]
        self._upstream = (loopback_hosts(upstream[0], "upstream")[0], upstream[1])
        self.schedule = resolve(schedule) if isinstance(schedule, str) else schedule
        self.shaper = LinkShaper(self.schedule, seed)
        self.idle_timeout_s = idle_timeout_s
        self.tcp_passthrough = tcp_passthrough
        self._loop: asyncio.AbstractEventLoop | None = None
        self._listeners: list[socket.socket] = []
        self._tcp_servers: list[asyncio.Server] = []
        self._tcp_tasks: set[asyncio.Task[None]] = set()
        self._clients: dict[tuple[int, Any], _Client] = {}
        self._heap: list[_Pending] = []
        self._seq = 0
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = float("inf")
        self._sweeper: asyncio.TimerHandle | None = None
        self._lateness_s: deque[float] = deque(maxlen=_LATENESS_SAMPLES)
        self._send_errors = 0
        self.port = 0

    # -- life cycle -------------------------------------------------------------------

    async def start(self) -> NetworkEmulator:
        self._loop = asyncio.get_running_loop()
        udp, tcp = self._bind()
        self._listeners = udp
        self.port = udp[0].getsockname()[1]
        for index, sock in enumerate(udp):
            self._loop.add_reader(sock.fileno(), self._on_client_readable, index)
        for sock in tcp:
            self._tcp_servers.append(await asyncio.start_server(self._pass_tcp, sock=sock))
        self.shaper.restart_schedule(self._loop.time())
        self._sweeper = self._loop.call_later(self._sweep_every_s, self._sweep_idle)
        hosts = ", ".join(self._listen_hosts)
        log.info("network emulator on %s port %d -> %s", hosts, self.port, self._upstream)
        return self

    async def stop(self) -> None:
        loop = self._loop
        if loop is None:
            return
        for handle in (self._timer, self._sweeper):
            if handle is not None:
                handle.cancel()
        self._timer = self._sweeper = None
        self._timer_at = float("inf")
        self._heap.clear()
        for client in list(self._clients.values()):
            self._close_client(client)
        for sock in self._listeners:
            loop.remove_reader(sock.fileno())
            sock.close()
        self._listeners = []
        for server in self._tcp_servers:
            server.close()
        handlers = list(self._tcp_tasks)
        for task in handlers:
            task.cancel()
        # Awaited, not only cancelled: EmulatorThread closes the loop right after, and a
        # handler still unwinding then was finished by the garbage collector, closing
        # its writers on the closed loop ('Event loop is closed').
        await asyncio.gather(*handlers, return_exceptions=True)
        for server in self._tcp_servers:
            await server.wait_closed()
        self._tcp_servers = []
        self._loop = None

    async def __aenter__(self) -> NetworkEmulator:
        return await self.start()

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()

    def restart_schedule(self) -> None:
        """Schedule time 0 is now (a benchmark calls this when its stream starts)."""
        self.shaper.restart_schedule(self._now())

    def _bind(self) -> tuple[list[socket.socket], list[socket.socket]]:
        # Port 0 asks the kernel for the first socket's port; the others must then get
        # the same one, which another process may hold: try again with a new port.
        for _ in range(20):
            udp: list[socket.socket] = []
            tcp: list[socket.socket] = []
            port = self._listen_port
            try:
                for host in self._listen_hosts:
                    try:
                        sock = _bound_udp_socket(host, port)
                    except OSError as exc:
                        if host == "::1" and udp and exc.errno in _NO_IPV6:
                            log.warning("emulator: no IPv6 loopback here; 127.0.0.1 only")
                            continue
                        raise
                    udp.append(sock)
                    port = sock.getsockname()[1]
                    if self.tcp_passthrough:
                        server = socket.socket(_family(host), socket.SOCK_STREAM)
                        tcp.append(server)
                        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                        server.bind((host, port))
                        server.listen(64)
                        server.setblocking(False)
                return udp, tcp
            except OSError as exc:
                for sock in udp + tcp:
                    sock.close()
                if exc.errno != errno.EADDRINUSE or self._listen_port != 0:
                    raise
        raise OSError(errno.EADDRINUSE, "no free port for every listen address")

    # -- packets ----------------------------------------------------------------------

    def _now(self) -> float:
        assert self._loop is not None, "the emulator is not started"
        return self._loop.time()

    def _wall_minus_loop(self) -> float:
        return time.time() - self._now()

    def _on_client_readable(self, index: int) -> None:
        listener = self._listeners[index]
        wall_minus_loop = self._wall_minus_loop()
        for _ in range(_READ_BATCH):
            try:
                data, ancillary, _, address = listener.recvmsg(_MAX_DATAGRAM, _ANCILLARY_SPACE)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue  # an ICMP error for an earlier send to a client that left
            now = self._now()
            client = self._clients.get((index, address))
            if client is None:
                client = self._open_client(index, address, now)
            client.last_seen = now
            arrived = _arrival(ancillary, wall_minus_loop, now)
            decision = self.shaper.up.offer(len(data), arrived)
            if decision.fate is Fate.DELIVER:
                self._hold(decision.depart_at, client.upstream, data, None)

    def _open_client(self, index: int, address: Any, now: float) -> _Client:
        assert self._loop is not None
        upstream = _udp_socket(_family(self._upstream[0]))
        upstream.connect(self._upstream)
        client = _Client((index, address), self._listeners[index], address, upstream, now)
        self._clients[(index, address)] = client
        self._loop.add_reader(upstream.fileno(), self._on_upstream_readable, client)
        log.debug("emulator: new client %s via port %d", address, upstream.getsockname()[1])
        return client

    def _close_client(self, client: _Client) -> None:
        assert self._loop is not None
        self._loop.remove_reader(client.upstream.fileno())
        client.upstream.close()
        self._clients.pop(client.key, None)

    def _on_upstream_readable(self, client: _Client) -> None:
        wall_minus_loop = self._wall_minus_loop()
        for _ in range(_READ_BATCH):
            try:
                data, ancillary, _, _ = client.upstream.recvmsg(_MAX_DATAGRAM, _ANCILLARY_SPACE)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue  # ICMP port unreachable: the relay is not (yet) there
            now = self._now()
            client.last_seen = now
            decision = self.shaper.down.offer(len(data), _arrival(ancillary, wall_minus_loop, now))
            if decision.fate is Fate.DELIVER:
                self._hold(decision.depart_at, client.listener, data, client.address)

    def _hold(self, depart_at: float, sock: socket.socket, data: bytes, to: Any) -> None:
        self._seq += 1
        heapq.heappush(self._heap, _Pending(depart_at, self._seq, sock, data, to))
        if depart_at < self._timer_at:
            self._arm(depart_at)

    def _arm(self, depart_at: float) -> None:
        assert self._loop is not None
        if self._timer is not None:
            self._timer.cancel()
        self._timer_at = depart_at
        self._timer = self._loop.call_at(depart_at - _EARLY_S, self._release)

    def _release(self) -> None:
        self._timer = None
        self._timer_at = float("inf")
        now = self._now()
        heap = self._heap
        while heap and heap[0].depart_at <= now + _EARLY_S:
            packet = heapq.heappop(heap)
            self._lateness_s.append(now - packet.depart_at)
            try:
                if packet.to is None:
                    packet.sock.send(packet.data)
                else:
                    packet.sock.sendto(packet.data, packet.to)
            except OSError:
                # Full socket buffer, a closed mapping, an ICMP error: the packet is lost,
                # as on a real network, and counted so a test can tell it from shaping.
                self._send_errors += 1
        if heap:
            self._arm(heap[0].depart_at)

    # -- idle mappings ----------------------------------------------------------------

    @property
    def _sweep_every_s(self) -> float:
        return max(0.05, min(5.0, self.idle_timeout_s / 3.0))

    def _sweep_idle(self) -> None:
        assert self._loop is not None
        now = self._now()
        for client in list(self._clients.values()):
            if now - client.last_seen > self.idle_timeout_s:
                log.debug("emulator: client %s idle, mapping closed", client.address)
                self._close_client(client)
        self._sweeper = self._loop.call_later(self._sweep_every_s, self._sweep_idle)

    # -- TCP, unshaped ----------------------------------------------------------------

    async def _pass_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tcp_tasks.add(task)
        try:
            up_reader, up_writer = await asyncio.open_connection(*self._upstream)
        except OSError:
            writer.close()
            self._tcp_tasks.discard(task)
            return
        try:
            await asyncio.gather(_pump(reader, up_writer), _pump(up_reader, writer))
        except asyncio.CancelledError:
            # stop() ends the pass-through by cancelling it. The task must still end
            # normally: asyncio's stream server asks a finished handler task for its
            # exception, which on a cancelled task raises, and the loop logged that as
            # 'Exception in callback ...' at every benchmark profile's end.
            pass
        finally:
            for w in (writer, up_writer):
                w.close()
            self._tcp_tasks.discard(task)

    # -- figures ----------------------------------------------------------------------

    @property
    def clients(self) -> int:
        return len(self._clients)

    def stats(self) -> dict[str, Any]:
        """Counters per direction, the step in force, and how late packets really left."""
        now = self._now() if self._loop is not None else self.shaper.origin
        step = self.shaper.step_index(now)
        late = sorted(self._lateness_s)
        late_ms: dict[str, float] = {}
        if late:
            late_ms = {
                "p50": 1000.0 * statistics.median(late),
                "p99": 1000.0 * late[min(len(late) - 1, int(0.99 * len(late)))],
                "max": 1000.0 * late[-1],
                "min": 1000.0 * late[0],
            }
        return {
            "elapsed_s": now - self.shaper.origin,
            "step": step,
            "step_at_s": self.schedule.steps[step].at_s,
            "clients": len(self._clients),
            "in_flight": len(self._heap),
            "send_errors": self._send_errors,
            "down": self.shaper.down.counters.as_dict(),
            "up": self.shaper.up.counters.as_dict(),
            "release_late_ms": late_ms,
        }


async def _pump(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    with contextlib.suppress(ConnectionError, asyncio.CancelledError):
        while data := await reader.read(65536):
            writer.write(data)
            await writer.drain()
    with contextlib.suppress(OSError, RuntimeError):
        if writer.can_write_eof():
            writer.write_eof()


class EmulatorThread:
    """A ``NetworkEmulator`` on its own event loop in a daemon thread.

    ``with EmulatorThread(upstream=("127.0.0.1", port), schedule="lte") as net:``
    then point the viewer at ``net.port``. Arguments are NetworkEmulator's.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.emulator = NetworkEmulator(*args, **kwargs)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return self.emulator.port

    def start(self, timeout_s: float = 10.0) -> EmulatorThread:
        loop = emulator_loop()
        self._loop = loop
        self._thread = threading.Thread(target=loop.run_forever, name="netem", daemon=True)
        self._thread.start()
        self._call(self.emulator.start(), timeout_s)
        return self

    def stop(self, timeout_s: float = 10.0) -> None:
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        try:
            self._call(self.emulator.stop(), timeout_s)
        finally:
            loop.call_soon_threadsafe(loop.stop)
            thread.join(timeout_s)
            if not thread.is_alive():
                loop.close()
            self._loop = self._thread = None

    def stats(self) -> dict[str, Any]:
        return self._in_loop(self.emulator.stats)

    def restart_schedule(self) -> None:
        self._in_loop(self.emulator.restart_schedule)

    def _in_loop(self, fn: Callable[[], T]) -> T:
        async def call() -> T:
            return fn()

        return self._call(call(), 10.0)

    def _call(self, coro: Coroutine[Any, Any, T], timeout_s: float) -> T:
        if self._loop is None:
            coro.close()
            raise RuntimeError("the emulator thread is not started")
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout_s)

    def __enter__(self) -> EmulatorThread:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
