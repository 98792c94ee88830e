"""The relay process: aiohttp app with the nodes' ingest WebSocket (``/ingest``), the browsers'
Socket.IO server (``/ui``), the HTTP API and storage.

``serve(config)`` runs it until SIGINT/SIGTERM; ``start_relay(config)`` starts it on a running loop
(tests, benchmarks): the settings are one :class:`~dcuscope.relay.config.RelayConfig`. The page of ``ui/static/`` is served at ``/``, the
Prometheus metrics at ``/metrics`` (:mod:`dcuscope.relay.export.metrics`). Beside it,
the UDP clock exchange (:mod:`dcuscope.relay.clock.udp`) listens on ``clock_port``: by default the HTTP
port's number, 0 turns it off.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import socketio
from aiohttp import web

from dcuscope.core import signals
from dcuscope.protocol.wire import INGEST_PATH, MAX_MESSAGE_BYTES
from dcuscope.relay.api.compare import add_compare_routes
from dcuscope.relay.api.fanout import FanoutHealth, FleetManager, create_manager
from dcuscope.relay.api.fleet import Fleet
from dcuscope.relay.api.history import add_history_routes
from dcuscope.relay.api.journeys import add_journey_routes
from dcuscope.relay.api.interest import Interest
from dcuscope.relay.api.routes import add_routes
from dcuscope.relay.api.sessions import add_session_routes
from dcuscope.relay.api.sio import SIO_PATH, create_sio, sio_errors
from dcuscope.relay.api.ui import Ticker, UiNamespace
from dcuscope.relay.clock.udp import ClockUdp
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.errors import RelayError
from dcuscope.relay.export.metrics import RelayCollector, add_metrics_route
from dcuscope.relay.export.otlp import OtlpExporter
from dcuscope.relay.guard import badrequests, lograte, redact
from dcuscope.relay.guard.connections import ConnGuard, GuardedSite, fit_descriptors
from dcuscope.relay.guard.hostcheck import HostCheck
from dcuscope.relay.guard.policy import Action, Policy, declare
from dcuscope.relay.guard.signin import add_signin_routes, from_address
from dcuscope.relay.heap import Reclaimer
from dcuscope.relay.ingest.endpoint import SYNCS_KEPT, Ingest
from dcuscope.relay.live.state import RelayState
from dcuscope.relay.store.compactor import Compactor
from dcuscope.relay.store.retention import retain
from dcuscope.relay.store.writer import Storage

UI_DIR = Path(__file__).resolve().parents[1] / "ui" / "static"
LOOPBACK = ("127.0.0.1", "::1", "localhost")
LOG_FLUSH_S = 10.0
STOP_BROWSERS_S = 2.0
"""How long a stopping relay waits for its browsers' connections to close."""
STOP_REQUESTS_S = 1.5
"""How long a stopping relay lets requests in progress finish before it cancels them, and then waits
for them to end (aiohttp's 60 s held a stop for a minute on a page's Socket.IO request that outlives
its closed engine.io socket). The nodes' websockets are closed before; what a cancelled ingest had
not acknowledged, its node sends again wherever it resumes."""
REFUSALS = ("peer_cap", "tcp_cap", "header_timeout", "hello_timeout", "host", "proxy_header", "plaintext",
            "tls_timeout", "tls_handshake", "credential_missing", "credential_wrong", "certificate_missing", "role",
            "undeclared")
PLACEHOLDER = """<!doctype html><html><head><meta charset="utf-8"><title>dcuscope relay</title></head>
<body><h1>dcuscope relay</h1><p>The UI is not installed (ui/static/index.html). The JSON API is at
<a href="/api/nodes">/api/nodes</a>, <a href="/api/sessions">/api/sessions</a>,
/api/stats?node=NAME, /api/frames?node=NAME.</p></body></html>"""

log = logging.getLogger(__name__)


@dataclass
class Relay:
    state: RelayState
    storage: Storage
    sio: socketio.AsyncServer
    ingest: Ingest
    ui: UiNamespace
    ticker: Ticker
    fleet: Fleet
    fanout: FanoutHealth
    guard: ConnGuard
    metrics: RelayCollector
    """``/metrics``' collector; exporters add families to its ``extra``."""
    runner: web.AppRunner | None = None
    port: int = 0
    otlp: OtlpExporter | None = None
    """The OTLP trace exporter (``--otlp``), if any."""
    reclaimer: Reclaimer | None = None
    """Gives back the memory of runs that left it (:mod:`dcuscope.relay.heap`)."""
    compactor: Compactor | None = None
    """Moves old batches into segments (:mod:`dcuscope.relay.store.compaction`; None: ``--compact-after 0``)."""
    stop_said: str = ""
    """What the stop rolled up (:meth:`Compactor.roll_up`), for the relay's last lines."""
    _task: asyncio.Task | None = None
    _retention: asyncio.Task | None = None
    _reclaim: asyncio.Task | None = None

    @property
    def clock_port(self) -> int:
        """The UDP clock exchange's port (0: not offered)."""
        return self.ingest.clock_udp.port if self.ingest.clock_udp is not None else 0

    async def stop(self) -> None:
        for task in (self._task, self._retention, self._reclaim):
            if task is not None:
                task.cancel()
        if self.ingest.clock_udp is not None:
            self.ingest.clock_udp.stop()
        # No new connection from here on: a page told to disconnect below reconnects at once, and the
        # web runner would then wait out its new websocket (15 s and more with a page open).
        if self.runner is not None:
            for site in list(self.runner.sites):
                await site.stop()
        # Close every client's websocket first: the web runner would wait out their pings.
        await self.ingest.close_all()
        if self.otlp is not None:
            await self.otlp.stop()
        await self.ticker.interest.close()
        if self.sio.eio.sockets:  # the browsers' too: the web runner would wait out their pings
            try:
                await asyncio.wait_for(self.sio.eio.disconnect(), STOP_BROWSERS_S)
            except asyncio.TimeoutError:  # a client that does not answer: the runner closes it
                pass
            except ValueError:  # the last one left meanwhile: engine.io's disconnect waits on an empty set
                pass
        await self.sio.shutdown()
        if isinstance(self.sio.manager, FleetManager):
            await self.sio.manager.close()
        if self.runner is not None:
            await self.runner.cleanup()
        self.fleet.close()
        if self.compactor is not None:
            await asyncio.to_thread(self.compactor.stop)
        self.storage.stop()
        if self.compactor is not None:  # the writer committed the last batches: the runs' tails are stored
            self.stop_said = await asyncio.to_thread(self.compactor.roll_up)


def create_app(config: RelayConfig) -> tuple[web.Application, Relay]:
    """The relay's app, as ``config`` says (:class:`~dcuscope.relay.config.RelayConfig`). Who may do what is
    :mod:`dcuscope.relay.guard.policy`'s; while anyone may read, requests must name an IP, localhost or one of
    ``allow_hosts`` (:mod:`dcuscope.relay.guard.hostcheck`). ``otlp`` exports sampled frames as traces
    (:mod:`dcuscope.relay.export.otlp`; its thread starts with :func:`start_relay`); ``trusted_proxies``: peers
    whose connections start with a PROXY header naming the client (:mod:`dcuscope.relay.guard.proxy`); ``redis``
    carries every relay's pushes to every relay's browsers (:mod:`dcuscope.relay.api.fanout`); batches stored
    ``compact_after_s`` are compacted (:mod:`dcuscope.relay.store.compaction`; 0: never); ``tls``: the port speaks
    HTTPS only (:mod:`dcuscope.relay.guard.tls`; with its client CA, ``/ingest`` takes only nodes with a
    certificate it signed); a PostgreSQL store's writes not answered within ``store_timeout_s`` are
    cancelled and sent again (:mod:`dcuscope.relay.store.writer`)."""
    c = config
    refused: Counter = Counter()
    policy = Policy(c.credentials, refused, certified=c.tls is not None and c.tls.verifies_clients)  # a token given twice: before anything starts
    limits = fit_descriptors(c.limits)
    # The name other relays sharing the store see (/api/health's store.relays).
    storage = Storage(c.db, name=f"{socket.gethostname()} pid {os.getpid()}", timeout_s=c.store_timeout_s)
    state = RelayState(storage, c.clock, c.live, limits, c.frame_limits)
    state.relay_name = c.name or ""
    manager, fanout = create_manager(c.redis)
    sio = create_sio(manager)
    ingest = Ingest(state, limits)
    storage.on_owners_lost = lambda: _background(ingest.let_go())
    storage.on_runs_lost = lambda runs: _background(ingest.let_go_runs(runs))
    fleet = Fleet(state)
    ui = UiNamespace(state, fleet, policy)
    sio.register_namespace(ui)
    guard = ConnGuard(limits, refused, c.trusted_proxies, c.tls)
    # The guard's first: a request refused further in still counts as one the connection sent.
    middlewares = [guard.middleware]
    if policy.reads_open:
        # Nodes' own tokens (node_tokens) guard /ingest, not the API or the page.
        middlewares.append(HostCheck(c.allow_hosts, refused, INGEST_PATH if c.credentials.nodes else None).middleware)
    app = web.Application(client_max_size=MAX_MESSAGE_BYTES, middlewares=[*middlewares, policy.middleware, sio_errors])
    declare(app, Action.INGEST, app.router.add_get(INGEST_PATH, ingest.handle))
    sio.attach(app)
    declare(app, Action.SOCKET, *(r for r in app.router.resources() if r.canonical.startswith(SIO_PATH.rstrip("/"))))
    interest = Interest(ui.wishes, c.redis, fanout, me=f"{socket.gethostname()} pid {os.getpid()} {id(state):x}")
    ticker = Ticker(state, ui, fleet, interest, c.push_hz)
    reclaimer = Reclaimer(lambda: state.released)
    exporter = OtlpExporter(c.otlp, state) if c.otlp is not None else None
    compactor = Compactor(c.db, c.compact_after_s, storage.name, storage.owner) if c.compact_after_s > 0 else None

    def refusals() -> dict[str, int]:
        refused["hello_timeout"] = ingest.hello_timeouts
        return {**state.refused, **{k: refused[k] for k in REFUSALS}}

    def counters() -> dict:
        udp = ingest.clock_udp
        return {"rejected": ingest.rejected, "clock_rejected": ingest.clock_rejected, "paused": ingest.paused,
                "clock_udp": dict(udp.counts, port=udp.port, keys=udp.keys) if udp is not None else None,
                "refused": refusals(),
                "connections": {"tcp": guard.open, "ingest": ingest.connected},
                "proxy": {"trusted": c.trusted_proxies.as_list(), "proxied": guard.proxied,
                          "proxied_open": guard.proxied_open} if c.trusted_proxies else None,
                "relay": state.relay_name, "fanout": fanout.view(), "mirrored_runs": len(fleet.mirrors or ()),
                "pushes": ticker.pushes, "commits": storage.commits, "batches": storage.batches_written,
                "limits": limits.as_dict(), "released_runs": state.released, "memory": state.memory_view(),
                "heap": reclaimer.view(), "compaction": compactor.view() if compactor is not None else None,
                "otlp": exporter.view() if exporter is not None else None}

    add_routes(app, state, fleet, ui, counters)
    add_compare_routes(app, add_session_routes(app, state))
    add_history_routes(app, state)
    add_journey_routes(app, state)
    metrics = RelayCollector(state, ingest, guard, refusals)
    add_metrics_route(app, metrics)
    add_signin_routes(app, policy)
    _add_ui(app, policy)
    if exporter is not None:
        exporter.attach(metrics)
    return app, Relay(state, storage, sio, ingest, ui, ticker, fleet, fanout, guard, metrics, otlp=exporter,
                      reclaimer=reclaimer, compactor=compactor)


_tasks: set[asyncio.Task] = set()


def _background(coro) -> None:
    task = asyncio.ensure_future(coro)
    _tasks.add(task)  # held: the loop keeps only weak references to tasks
    task.add_done_callback(_tasks.discard)


def _add_ui(app: web.Application, policy: Policy) -> None:
    index = UI_DIR / "index.html"
    icon = UI_DIR / "favicon.svg"

    async def root(request: web.Request) -> web.StreamResponse:
        from_address(request, policy)  # ?token=T: signed in and sent on without it
        if index.is_file():
            return web.FileResponse(index)
        return web.Response(text=PLACEHOLDER, content_type="text/html")

    async def favicon(request: web.Request) -> web.StreamResponse:
        # The page links favicon.svg; browsers on pages that link none (the JSON API's) ask here.
        if icon.is_file():
            return web.FileResponse(icon, headers={"Content-Type": "image/svg+xml"})
        raise web.HTTPNotFound()

    # The page's shell and files hold no data: it asks for that with its cookie.
    declare(app, Action.PUBLIC, app.router.add_get("/", root), app.router.add_get("/favicon.ico", favicon))
    if UI_DIR.is_dir():
        # Registered last: every other route wins; aiohttp refuses paths leaving the folder.
        declare(app, Action.PUBLIC, app.router.add_static("/", UI_DIR, follow_symlinks=False))


async def start_relay(config: RelayConfig) -> Relay:
    """Start a relay on the running loop, as ``config`` says; ``port=0`` picks a free port (see ``Relay.port``).
    ``clock_port``: UDP port of the clock exchange (None: the HTTP port's number; 0: none); ``reuse_port``: share
    the port with the host's other relay processes (``--workers``); ``retention``: delete sessions and rollups
    older than it says (:mod:`dcuscope.relay.store.retention`; None: keep all)."""
    host, port = config.host, config.port
    app, relay = create_app(config)
    relay.storage.start(asyncio.get_running_loop())
    runner = web.AppRunner(app, access_log=None, handle_signals=False,
                           keepalive_timeout=relay.guard.limits.keepalive_s, shutdown_timeout=STOP_REQUESTS_S)
    await runner.setup()
    site = GuardedSite(runner, host, port, relay.guard, reuse_port=config.reuse_port)
    try:
        await site.start()
    except OSError as exc:
        await runner.cleanup()
        relay.storage.stop()
        raise RelayError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from exc
    relay.runner = runner
    relay.port = site.port
    if not relay.state.relay_name:  # workers sharing a port: told apart by their process
        relay.state.relay_name = f"{socket.gethostname()}:{relay.port}" + (f"#{os.getpid()}" if config.reuse_port else "")
    try:
        _start_clock_udp(relay, host, config.clock_port)
    except RelayError:
        await runner.cleanup()
        relay.storage.stop()
        raise
    if not relay.sio.manager_initialized:
        # python-socketio starts its manager at the first browser's connection; the Redis
        # subscriber must run before (this relay's pushes reach other relays' browsers meanwhile).
        relay.sio.manager_initialized = True
        relay.sio.manager.initialize()
    relay._task = asyncio.create_task(relay.ticker.run())
    relay._reclaim = asyncio.create_task(relay.reclaimer.run())
    if config.retention is not None:
        relay._retention = asyncio.create_task(retain(relay.storage, config.retention))
    if relay.otlp is not None:
        relay.otlp.start()
    if relay.compactor is not None:
        relay.compactor.start()
    return relay


def _start_clock_udp(relay: Relay, host: str, clock_port: int | None) -> None:
    """Listen for UDP clock exchanges. A port asked for that cannot be had is an error; the
    default one (the HTTP port's number) taken leaves nodes on the WebSocket exchange, said once."""
    if clock_port == 0:
        return
    udp = ClockUdp(relay.guard.limits, SYNCS_KEPT)
    try:
        udp.start(host, relay.port if clock_port is None else clock_port)
    except OSError as exc:
        if clock_port is not None:
            raise RelayError(f"--clock-port {clock_port}: cannot listen on UDP {host}:{clock_port}: "
                             f"{exc.strerror or exc}") from exc
        log.warning("no UDP clock exchange: cannot listen on UDP %s:%d (%s); nodes exchange clock samples over "
                    "their WebSocket (--clock-port N picks another port)", host, relay.port, exc.strerror or exc)
        return
    relay.ingest.clock_udp = udp


def serve(config: RelayConfig) -> None:
    """Run the relay until SIGINT or SIGTERM, as ``config`` says."""
    if config.host not in LOOPBACK and not config.credentials.any:
        log.warning("relay listens on %s without --token: anyone who can reach it may feed or read it", config.host)
    badrequests.install()
    rate = lograte.install(config.limits.log_repeats_per_min)
    redact.install(config.credentials.secrets())
    asyncio.run(_serve(config, rate))


async def _serve(config: RelayConfig, rate: lograte.RateFilter) -> None:
    relay = await start_relay(config)
    flusher = asyncio.create_task(_flush_log(rate))
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if relay.guard.tls is not None:  # a renewed certificate, without a restart
        loop.add_signal_handler(signal.SIGHUP, relay.guard.tls.reload)
    if signals.held() is not None:  # Ctrl-C while starting up
        stop.set()
    udp = f"UDP clock exchange on port {relay.clock_port}" if relay.clock_port else "no UDP clock exchange"
    scheme = "https" if relay.guard.tls is not None else "http"
    print(f"dcuscope relay: listening on {scheme}://{config.host}:{relay.port} (db {relay.storage.location}, clock {config.clock}; "
          f"{udp})", flush=True)
    try:
        await stop.wait()
    finally:
        flusher.cancel()
        await relay.stop()
        rate.flush(everything=True)
        if relay.stop_said:
            print(f"dcuscope relay: {relay.stop_said}", file=sys.stderr, flush=True)
        print("dcuscope relay: stopped", file=sys.stderr, flush=True)


async def _flush_log(rate: lograte.RateFilter) -> None:
    """Summarise the messages the log's rate bound held back, now and then."""
    while True:
        await asyncio.sleep(LOG_FLUSH_S)
        rate.flush()
