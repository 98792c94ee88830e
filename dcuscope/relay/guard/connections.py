"""The relay's TCP-level guard, in front of aiohttp's protocol: no client holds more than its
share of connections, or holds one without using it.

:class:`GuardedSite` is an aiohttp site that accepts connections itself (instead of asyncio's
server) and hands each admitted socket to :class:`ConnGuard`, which

- caps TCP connections per peer IP (``connections_per_peer``) and in all (``tcp_connections``):
  a connection beyond a cap is closed as soon as it is accepted, before aiohttp sees it; at
  a cap an idle connection (one waiting for a request head, or an idle keep-alive one) makes
  room first, oldest first: the peer's own at its cap, anyone's at the total cap. Silent
  connections cannot starve clients that talk, and a host's idle keep-alive connections (a
  browser keeps six per page) cannot lock out its next page or request; only connections that
  are busy (a request in progress, a WebSocket) hold a place for good;
- closes a connection that has not sent a complete request head within ``header_timeout_s``
  of connecting or of the first byte of its next request (slowloris); a request has "arrived"
  once :meth:`ConnGuard.middleware` sees it, and keep-alive idle time is aiohttp's
  ``keepalive_timeout`` (``keepalive_s``);
- behind a load balancer (``--trusted-proxy``, :mod:`dcuscope.relay.guard.proxy`), reads the PROXY header
  a trusted proxy's connection starts with before aiohttp sees it: the connection then counts
  against the cap of its client's address, not the proxy's, and aiohttp's ``request.remote``
  (the transport's ``peername``) is the client's. It takes a place in the total cap while the
  header comes, as any connection that has not sent its request head (so it may make room, and
  ``header_timeout_s`` covers header and request head together); one whose header is malformed,
  or does not come in time, is closed and counted (``proxy_header``);
- with TLS (``--tls-cert``, :mod:`dcuscope.relay.guard.tls`), peeks at a connection's first byte (after the
  PROXY header, if any): a TLS handshake's (0x16) goes to asyncio's TLS transport, anything else is
  answered one short HTTP 400 and closed (``plaintext``). The connection holds its place and may
  make room while it handshakes, as one waiting for its request head; header, peek and handshake
  must be done within ``header_timeout_s`` (else ``tls_timeout``), and a failed handshake (an
  unknown client certificate, a client that dislikes the relay's) is counted (``tls_handshake``).
  aiohttp sees the connection once the handshake is done, and its request head then has another
  ``header_timeout_s``.

Accepting one socket at a time and closing a refused one at once keeps the descriptors in use
within ``tcp_connections`` plus one: :func:`fit_descriptors` raises the process's soft
RLIMIT_NOFILE towards its hard limit and lowers ``tcp_connections`` to what is left once
:data:`RESERVED_FDS` are kept for everything else, so accept() never fails with EMFILE.
"""

from __future__ import annotations

import asyncio
import logging
import resource
import socket
import ssl
from collections import Counter, OrderedDict
from dataclasses import replace

from aiohttp import web

from dcuscope.core.pycompat import ASYNC_TIMEOUTS, timeout
from dcuscope.relay.guard.limits import Limits
from dcuscope.relay.guard.proxy import (V2_FIXED_BYTES, V2_SIGNATURE, ProxyHeader, ProxyHeaderError, TrustedProxies,
                               parse_header)
from dcuscope.relay.guard.tls import ServerTls, refused_certificate

RESERVED_FDS = 128
"""Descriptors kept for all but client connections: SQLite (the writer and the session readers'
threads: file, -wal and -shm each), the listening sockets, the event loop's selector and
self-pipe, stdio, files being served, and idle connections being closed to make room."""
EVICTING = 16
"""Idle connections that may be closing at once to make room (they leave on the next loop turn)."""
ACCEPT_BURST = 64
"""Connections accepted in a row before the loop lets other work run (a flood cannot starve it)."""
ACCEPT_RETRY_S = 0.5
TLS_HANDSHAKE = 0x16
"""The first byte of a TLS record that starts a handshake (ClientHello)."""
PLAINTEXT_REPLY = (b"HTTP/1.1 400 Bad Request\r\nContent-Type: text/plain\r\nConnection: close\r\n"
                   b"Content-Length: 28\r\n\r\nthis port speaks HTTPS only\n")

log = logging.getLogger(__name__)


def fit_descriptors(limits: Limits) -> Limits:
    """``limits`` with ``tcp_connections`` lowered to fit RLIMIT_NOFILE, raised first as far as allowed."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 16)
    if soft != resource.RLIM_INFINITY and soft < want:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
            soft = want
        except (ValueError, OSError):  # a sandbox may refuse: live with the soft limit
            pass
    room = max(1, soft - RESERVED_FDS) if soft != resource.RLIM_INFINITY else limits.tcp_connections
    if room < limits.tcp_connections:
        log.info("tcp_connections lowered from %d to %d to fit the file descriptor limit (%d)",
                 limits.tcp_connections, room, soft)
        return replace(limits, tcp_connections=room)
    return limits


class ConnGuard:
    """Admits, times and counts the relay's TCP connections (see the module docstring)."""

    def __init__(self, limits: Limits, refused: Counter, trusted: TrustedProxies = TrustedProxies(),
                 tls: ServerTls | None = None) -> None:
        self.limits = limits
        self.refused = refused
        """Shared with the other guards: ``peer_cap``, ``tcp_cap``, ``header_timeout``, ``proxy_header``,
        ``plaintext``, ``tls_timeout``, ``tls_handshake`` here."""
        self.trusted = trusted
        """Peers whose connections start with a PROXY header (``--trusted-proxy``)."""
        self.tls = tls
        """The port speaks TLS only (None: plain HTTP only)."""
        self._opening: set[_Guarded] = set()
        """Connections being read for a header, peeked at or handshaking (TLS): each holds its socket."""
        self.proxied = 0
        """Connections a trusted proxy's header gave a client address, so far."""
        self._open: set[_Guarded] = set()
        self._peers: Counter = Counter()
        self._idle: OrderedDict[_Guarded, None] = OrderedDict()
        """Connections without a request in progress, longest idle first: the ones that make room."""
        self._peer_idle: dict[str, OrderedDict[_Guarded, None]] = {}
        """The same, per peer (once a connection is counted under one)."""
        self._evicting = 0

    @property
    def open(self) -> int:
        """TCP connections held now."""
        return len(self._open)

    @property
    def proxied_open(self) -> int:
        """Connections held now whose address came from a PROXY header."""
        return sum(1 for conn in self._open if conn.proxied)

    def admit(self, peer: str | None) -> bool:
        """Whether a connection from ``peer`` may open now (closing an idle one to make room).
        ``peer`` None: a trusted proxy's connection, whose client :meth:`admit_client` admits once
        its header names it (the proxy's own address is under no per-peer cap)."""
        if peer is not None and not self._peer_room(peer):
            return False
        if len(self._open) - self._evicting < self.limits.tcp_connections:
            return True
        self.refused["tcp_cap"] += 1
        return self._make_room(self._idle)

    def admit_client(self, conn: "_Guarded", peer: str) -> bool:
        """Whether ``conn``, open and waiting for its PROXY header, may stay now that it named its
        client ``peer``; counted against ``peer``'s cap if so."""
        if not self._peer_room(peer):
            return False
        conn.peer = peer
        self._peers[peer] += 1
        if conn in self._idle:
            self._peer_idle.setdefault(peer, OrderedDict())[conn] = None
        return True

    def _peer_room(self, peer: str) -> bool:
        if self._peers[peer] < self.limits.connections_per_peer:
            return True
        self.refused["peer_cap"] += 1
        return self._make_room(self._peer_idle.get(peer))

    def _make_room(self, idle: OrderedDict | None) -> bool:
        """Close the longest-idle connection of ``idle`` to make room for a new one; whether it did."""
        if not idle or self._evicting >= EVICTING:
            return False
        oldest = next(iter(idle))
        self._evicting += 1
        oldest.close(evicted=True)
        self._uncount_peer(oldest)  # its place is free now, though it leaves on the next loop turn
        return True

    async def accept_loop(self, lsock: socket.socket, factory) -> None:
        """Accept connections on ``lsock`` for ever, each admitted one served by ``factory()``."""
        loop = asyncio.get_running_loop()
        while True:
            for _ in range(ACCEPT_BURST):
                try:
                    sock, addr = await loop.sock_accept(lsock)
                except OSError as exc:  # EMFILE despite the reserve: wait, never spin
                    log.warning("accepting a connection failed: %s", exc.strerror or exc)
                    await asyncio.sleep(ACCEPT_RETRY_S)
                    break
                peer = addr[0] if isinstance(addr, tuple) else str(addr)
                # Only a trusted proxy's connection is read for a header: nobody else may name an address.
                proxy = peer in self.trusted
                if not self.admit(None if proxy else peer):
                    sock.close()
                    continue
                if self.tls is not None:
                    self._open_tls(sock, _Guarded(self, factory, peer, proxy))
                    continue
                try:
                    await loop.connect_accepted_socket(lambda: _Guarded(self, factory, peer, proxy), sock)
                except OSError:  # the peer left meanwhile
                    sock.close()
            await asyncio.sleep(0)

    def _open_tls(self, sock: socket.socket, conn: "_Guarded") -> None:
        """Serve ``sock`` over TLS through ``conn``, which holds its place meanwhile."""
        self._opened(conn)
        conn.sock = sock
        conn.opening = asyncio.create_task(conn.open_tls(sock, self.tls.context))
        self._opening.add(conn)

    def cancel_opening(self) -> None:
        """Drop the connections not yet handed to aiohttp (the site stops)."""
        for conn in list(self._opening):
            conn.close()

    @web.middleware
    async def middleware(self, request: web.Request, handler) -> web.StreamResponse:
        """Mark the request's connection busy (its head arrived) while its handler runs."""
        transport = request.transport
        conn = transport.get_protocol() if transport is not None else None
        if not isinstance(conn, _Guarded):  # a site without the guard (tests' own sites)
            return await handler(request)
        conn.request_started()
        try:
            return await handler(request)
        finally:
            conn.request_done()

    # --- bookkeeping of _Guarded -----------------------------------------------------------------

    def _opened(self, conn: "_Guarded") -> None:
        if conn in self._open:  # a TLS connection, counted from its accept, is now handshaken
            return
        self._open.add(conn)
        if conn.peer is not None:  # a proxy's connection counts once its header names the client
            self._peers[conn.peer] += 1
        self._now_idle(conn)

    def _closed(self, conn: "_Guarded") -> None:
        self._opening.discard(conn)
        if conn not in self._open:
            return
        self._open.discard(conn)
        self._now_busy(conn)
        self._uncount_peer(conn)
        if conn.evicted:
            self._evicting -= 1

    def _uncount_peer(self, conn: "_Guarded") -> None:
        peer, conn.peer = conn.peer, None
        if peer is not None:
            self._peers[peer] -= 1
            if not self._peers[peer]:
                del self._peers[peer]

    def _now_idle(self, conn: "_Guarded") -> None:
        """``conn`` has no request in progress: the newest to make room."""
        self._idle[conn] = None
        if conn.peer is not None:
            self._peer_idle.setdefault(conn.peer, OrderedDict())[conn] = None

    def _now_busy(self, conn: "_Guarded") -> None:
        """``conn`` serves a request, or is leaving: it makes no room."""
        self._idle.pop(conn, None)
        idle = self._peer_idle.get(conn.peer) if conn.peer is not None else None
        if idle is not None:
            idle.pop(conn, None)
            if not idle:
                del self._peer_idle[conn.peer]


class _Guarded(asyncio.Protocol):
    """aiohttp's protocol for one connection, wrapped: the guard's timer and bookkeeping around it.
    A trusted proxy's connection (``proxy``) reaches aiohttp only once its PROXY header is read."""

    def __init__(self, guard: ConnGuard, factory, peer: str, proxy: bool = False) -> None:
        self.guard = guard
        self.peer: str | None = None if proxy else peer
        """The address the per-peer cap counts this connection under (None until a header names it)."""
        self.via = peer if proxy else None
        """The trusted proxy's address, for a proxied connection."""
        self.proxied = False
        """Whether the header named a client (not UNKNOWN or LOCAL)."""
        self.inner: asyncio.Protocol = factory()
        self.transport: asyncio.Transport | None = None
        self.busy = 0
        self.evicted = False
        self._timer: asyncio.TimerHandle | None = None
        self._header: bytearray | None = bytearray() if proxy else None
        """The start of the PROXY header while it comes; None once read, or for a direct connection."""
        self._serving = not proxy
        """Whether aiohttp has the connection (a proxied one: once its header is read and admitted)."""
        self.opening: asyncio.Task | None = None
        """A TLS connection's header, peek and handshake (:meth:`open_tls`), until aiohttp has it."""
        self.sock: socket.socket | None = None
        """A TLS connection's socket until :meth:`open_tls` starts (it then closes it, or hands it on)."""
        self._client: tuple | None = None
        """The client's address a PROXY header gave, for the transport's ``peername``."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport
        self.guard._opened(self)
        self._await_head()
        if self._client is not None:
            _set_peername(transport, self._client)
        if self._serving:
            self.inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        if self._header is not None:
            self._header_received(data)
            return
        if not self._serving:  # refused, closing
            return
        if self.busy == 0 and self._timer is None:
            self._await_head()  # the first bytes of the next request on a kept-alive connection
        self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        if self._header is not None:
            if self._header:  # a header cut short; nothing at all is a proxy's TCP health check
                self._refuse_header("the connection ended within the PROXY header")
            return False
        return self.inner.eof_received() if self._serving else False

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_timer()
        self.guard._closed(self)
        if self._serving:  # else aiohttp never saw the connection
            self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        if self._serving:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self._serving:
            self.inner.resume_writing()

    # --- the PROXY header of a trusted proxy's connection ------------------------------------------

    def _header_received(self, data: bytes) -> None:
        self._header += data
        try:
            header = parse_header(self._header)
        except ProxyHeaderError as exc:
            self._refuse_header(str(exc))
            return
        if header is None:
            return  # more to come, within header_timeout_s
        rest = bytes(self._header[header.length:])
        self._header = None
        if not self._admit(header):
            self.close()
            return
        self._serving = True
        self.inner.connection_made(self.transport)
        if rest:  # the client's first bytes, untouched
            self.data_received(rest)

    def _admit(self, header: ProxyHeader) -> bool:
        """Count the connection under its client's address (the proxy's for UNKNOWN and LOCAL) and
        make the transport's ``peername``, which aiohttp reads for ``request.remote``, the client's."""
        if header.client is None:
            return self.guard.admit_client(self, self.via)
        host, port = header.client
        if not self.guard.admit_client(self, host):
            return False
        self.proxied = True
        self.guard.proxied += 1
        self._client = (host, port) if ":" not in host else (host, port, 0, 0)
        if self.transport is not None:  # else (TLS) once the handshake gives the transport
            _set_peername(self.transport, self._client)
        return True

    def _refuse_header(self, why: str) -> None:
        self._header = None
        self.guard.refused["proxy_header"] += 1
        log.warning("closing a connection from trusted proxy %s: %s", self.via, why)
        self.close()

    def request_started(self) -> None:
        self.busy += 1
        self._cancel_timer()
        self.guard._now_busy(self)

    def request_done(self) -> None:
        self.busy -= 1
        if self.busy == 0 and self in self.guard._open and not self.evicted:
            self.guard._now_idle(self)

    def close(self, evicted: bool = False) -> None:
        self.evicted = evicted
        self.guard._now_busy(self)
        if self.transport is not None:
            self.transport.abort()
        elif self.opening is not None:
            self.opening.cancel()
            if self.sock is not None:
                # Not started yet (an accept burst's connection made room for a later one): a task
                # cancelled before its first step never runs its body, so nothing else would ever
                # close the socket or give its place back.
                self.sock.close()
                self.sock = None
                self.opening = None
                self.guard._closed(self)

    # --- TLS ----------------------------------------------------------------------------------------

    async def open_tls(self, sock: socket.socket, context) -> None:
        """Read the PROXY header (a trusted proxy's connection), peek at the first byte, and hand
        a TLS handshake to asyncio's TLS transport with this protocol; all within
        ``header_timeout_s``. Anything else is refused, and counted (see the module docstring)."""
        self.sock = None  # started: closed or handed on below, whatever happens
        loop = asyncio.get_running_loop()
        limit = self.guard.limits.header_timeout_s
        why = "tls_timeout"
        handed = False
        try:
            async with timeout(limit):
                if self._header is not None:
                    why = "proxy_header"
                    if not await self._read_proxy_header(loop, sock):
                        return
                    why = "tls_timeout"
                first = await _peek(loop, sock)
                if not first:
                    return  # closed without a byte: a TCP health check
                if first[0] != TLS_HANDSHAKE:
                    self.guard.refused["plaintext"] += 1
                    log.info("refused a plaintext request from %s: this port speaks HTTPS only", self._who())
                    try:
                        sock.send(PLAINTEXT_REPLY)
                    except OSError:
                        pass
                    return
                self._serving = True
                handed = True  # asyncio's transport owns the socket from here, and closes it on failure
                await loop.connect_accepted_socket(lambda: self, sock, ssl=context,
                                                   ssl_handshake_timeout=limit)
        except ASYNC_TIMEOUTS:
            if why == "proxy_header":
                log.warning("closing a connection from trusted proxy %s: no complete PROXY header within %g s",
                            self.via, limit)
            else:
                log.info("closed a connection from %s: no TLS handshake within %g s", self._who(), limit)
            self.guard.refused[why] += 1
        except ProxyHeaderError as exc:
            self.guard.refused["proxy_header"] += 1
            log.warning("closing a connection from trusted proxy %s: %s", self.via, exc)
        except ssl.SSLCertVerificationError as exc:  # the client's certificate: the operator must see why
            self.guard.refused["tls_handshake"] += 1
            why = refused_certificate(exc)
            log.warning("TLS handshake with %s failed: %s", self._who(), why, extra={"rate_key": (why, self._who())})
        except (OSError, ssl.SSLError) as exc:  # a failed handshake, or the peer left
            self.guard.refused["tls_handshake"] += 1
            reason = getattr(exc, "reason", None) if isinstance(exc, ssl.SSLError) else None
            reason = reason or "the client ended it (does it trust this relay's certificate?)"
            log.info("TLS handshake with %s failed: %s", self._who(), reason, extra={"rate_key": (reason, self._who())})
        finally:
            self.opening = None
            self.guard._opening.discard(self)
            if self.transport is None:  # never handshaken: aiohttp never saw it
                self._serving = False
                if not handed:
                    sock.close()
                self.guard._closed(self)

    def _who(self) -> str:
        """The client's address, as the log names it (a proxied client's, once its header named it)."""
        return self.peer or self.via or "?"

    async def _read_proxy_header(self, loop: asyncio.AbstractEventLoop, sock: socket.socket) -> bool:
        """Consume exactly the PROXY header (the TLS bytes after it stay in the socket) and admit
        its client; whether the connection goes on."""
        while True:
            chunk = await loop.sock_recv(sock, _header_wants(self._header))
            if not chunk:
                if self._header:
                    raise ProxyHeaderError("the connection ended within the PROXY header")
                return False  # a proxy's TCP health check
            self._header += chunk
            header = parse_header(self._header)
            if header is not None:
                self._header = None
                return self._admit(header)

    def _await_head(self) -> None:
        loop = asyncio.get_running_loop()
        self._timer = loop.call_later(self.guard.limits.header_timeout_s, self._head_overdue)

    def _head_overdue(self) -> None:
        self._timer = None
        if self._header is not None:
            self._refuse_header(f"no complete PROXY header within {self.guard.limits.header_timeout_s:g} s")
        elif self.busy == 0:
            self.guard.refused["header_timeout"] += 1
            self.close()

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None


class GuardedSite(web.BaseSite):
    """An aiohttp TCP site whose connections go through a :class:`ConnGuard`."""

    def __init__(self, runner: web.BaseRunner, host: str, port: int, guard: ConnGuard, backlog: int = 128,
                 reuse_port: bool = False) -> None:
        super().__init__(runner, backlog=backlog)
        self._host, self._port = host, port
        self._reuse_port = reuse_port
        """SO_REUSEPORT: relay processes of one host share the port, the kernel spreading connections."""
        self._guard = guard
        self._socks: list[socket.socket] = []
        self._tasks: list[asyncio.Task] = []

    @property
    def port(self) -> int:
        """The port listened on (the one picked for port 0, once started)."""
        return self._port

    @property
    def name(self) -> str:
        return f"{'https' if self._guard.tls is not None else 'http'}://{self._host}:{self.port}"

    async def start(self) -> None:
        await super().start()
        try:
            self._listen()
        except OSError:
            self._close_sockets()
            raise
        factory = self._runner.server
        self._tasks = [asyncio.create_task(self._guard.accept_loop(s, factory)) for s in self._socks]
        for task in self._tasks:
            task.add_done_callback(_report_end)

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        self._guard.cancel_opening()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._close_sockets()
        await super().stop()

    def _listen(self) -> None:
        """Listen on every address ``host`` names (as asyncio's create_server does); port 0 picks
        one free port, shared by all."""
        port = self._port
        infos = socket.getaddrinfo(self._host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        for family, kind, proto, _, addr in dict.fromkeys(infos):
            sock = socket.socket(family, kind, proto)
            self._socks.append(sock)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if self._reuse_port:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            if family == socket.AF_INET6:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            sock.bind((addr[0], port, *addr[2:]))
            sock.listen(self._backlog)
            sock.setblocking(False)
            port = port or sock.getsockname()[1]
        self._port = port

    def _close_sockets(self) -> None:
        for sock in self._socks:
            sock.close()


def _set_peername(transport: asyncio.BaseTransport, client: tuple) -> None:
    """Make ``client`` the transport's ``peername``, which aiohttp reads for ``request.remote``."""
    # asyncio's transports answer get_extra_info() from these dicts and offer no way to set them;
    # aiohttp reads peername only once it has the transport, which is after this. A TLS transport
    # asks its TLS protocol's dict first.
    ssl_protocol = getattr(transport, "_ssl_protocol", None)
    extra = getattr(ssl_protocol if ssl_protocol is not None else transport, "_extra", None)
    if isinstance(extra, dict):
        extra["proxy_peername"] = transport.get_extra_info("peername")
        extra["peername"] = client


def _header_wants(header: bytearray) -> int:
    """How many bytes a PROXY header being read may take next without reading past its end:
    a v2 header's whole rest once its length is known, else one (a v1 line ends with its CRLF)."""
    if len(header) >= V2_FIXED_BYTES and header.startswith(V2_SIGNATURE):
        return V2_FIXED_BYTES + int.from_bytes(header[14:16], "big") - len(header)
    return 1


async def _peek(loop: asyncio.AbstractEventLoop, sock: socket.socket) -> bytes:
    """The first byte waiting on ``sock``, left there (b"": the peer closed)."""
    while True:
        try:
            return sock.recv(1, socket.MSG_PEEK)
        except (BlockingIOError, InterruptedError):
            pass
        readable = loop.create_future()
        loop.add_reader(sock.fileno(), lambda: readable.done() or readable.set_result(None))
        try:
            await readable
        finally:
            loop.remove_reader(sock.fileno())


def _report_end(task: asyncio.Task) -> None:
    # An accept loop ends only when the site stops; any other end leaves the relay deaf: say so.
    if not task.cancelled() and task.exception() is not None:
        log.error("the relay stopped accepting connections", exc_info=task.exception())
