"""The relay's settings as one typed object: :class:`RelayConfig`, checked when it is made, built
once from the command line (:meth:`RelayConfig.from_args`, ``dcuscope relay``) or by a program or a
test (``RelayConfig(db=..., port=0)``), and handed whole to :func:`dcuscope.relay.server.serve`,
``start_relay`` and ``create_app``.

The messages of a bad value name the option that sets it, as the command line spells it.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from dcuscope.relay.clock.correction import CLOCK_MODES
from dcuscope.relay.errors import RelayError
from dcuscope.relay.export.otlpconfig import DEFAULT_EVERY, DEFAULT_QUEUE, DEFAULT_TIMEOUT_S, OtlpConfig, otlp_config
from dcuscope.relay.guard.auth import Credentials
from dcuscope.relay.guard.limits import Limits
from dcuscope.relay.guard.proxy import TrustedProxies
from dcuscope.relay.guard.tls import ServerTls
from dcuscope.relay.live.framelimits import FrameLimits
from dcuscope.relay.live.pairing import DEFAULT_PUSH_HZ
from dcuscope.relay.live.run import LiveConfig
from dcuscope.relay.store.base import STORE_TIMEOUT_S
from dcuscope.relay.store.compaction import COMPACT_AFTER_S
from dcuscope.relay.store.engines import is_url
from dcuscope.relay.store.retention import Retention, parse_retention

MAX_COMPACT_AFTER_S = 7 * 86_400.0
MIN_STORE_TIMEOUT_S, MAX_STORE_TIMEOUT_S = 0.5, 600.0
MIN_PUSH_HZ, MAX_PUSH_HZ = 0.5, 240.0
MAX_WORKERS = 64
MAX_NAME_CHARS = 100


@dataclass(frozen=True)
class RelayConfig:
    """Everything a relay runs with; each field is the option of ``dcuscope relay`` of that name."""

    db: str | Path = "dcuscope.db"
    """An SQLite file, or a PostgreSQL URL shared by many relays (``--db``)."""
    host: str = "127.0.0.1"
    port: int = 3000
    """0 picks a free one (``Relay.port`` says which)."""
    clock_port: int | None = None
    """UDP port of the clock exchange: None the HTTP port's number, 0 none."""
    clock: str = "auto"
    credentials: Credentials = Credentials()
    limits: Limits = Limits()
    live: LiveConfig = LiveConfig()
    push_hz: float = DEFAULT_PUSH_HZ
    allow_hosts: tuple[str, ...] = ()
    frame_limits: FrameLimits = FrameLimits()
    otlp: OtlpConfig | None = None
    trusted_proxies: TrustedProxies = TrustedProxies()
    redis: str | None = None
    """Checked and with ``--redis-ca`` put in (:func:`~dcuscope.relay.api.fanout.check_url`)."""
    name: str | None = None
    """How pages and other relays name this one (None: HOST:PORT once listening)."""
    compact_after_s: float = COMPACT_AFTER_S
    tls: ServerTls | None = None
    store_timeout_s: float = STORE_TIMEOUT_S
    retention: Retention | None = None
    workers: int = 1
    reuse_port: bool = False
    """Share the port with the host's other relay processes (a worker of ``--workers``)."""
    log_level: str = "WARNING"

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise RelayError(f"--port must be 0..65535, not {self.port}")
        if self.clock_port is not None and not 0 <= self.clock_port <= 65535:
            raise RelayError(f"--clock-port must be 0..65535, not {self.clock_port}")
        if self.clock not in CLOCK_MODES:
            raise RelayError(f"--clock must be one of {', '.join(CLOCK_MODES)}, not {self.clock!r}")
        if self.name is not None and (not 0 < len(self.name) <= MAX_NAME_CHARS or not self.name.isprintable()):
            raise RelayError(f"--name takes 1 to {MAX_NAME_CHARS} printable characters")
        if not MIN_PUSH_HZ <= self.push_hz <= MAX_PUSH_HZ:
            raise RelayError(f"--push-hz must be {MIN_PUSH_HZ:g}..{MAX_PUSH_HZ:g}, not {self.push_hz:g}")
        if not 0 <= self.compact_after_s <= MAX_COMPACT_AFTER_S:
            raise RelayError(f"--compact-after takes 0 (never) to {MAX_COMPACT_AFTER_S:g} seconds, not {self.compact_after_s:g}")
        if not MIN_STORE_TIMEOUT_S <= self.store_timeout_s <= MAX_STORE_TIMEOUT_S:
            raise RelayError(f"--store-timeout takes {MIN_STORE_TIMEOUT_S:g} to {MAX_STORE_TIMEOUT_S:g} seconds, "
                             f"not {self.store_timeout_s:g}")
        if self.workers != 1:
            if not 2 <= self.workers <= MAX_WORKERS:
                raise RelayError(f"--workers must be 1..{MAX_WORKERS}, not {self.workers}")
            if not is_url(self.db):
                raise RelayError("--workers N runs N relays on one store: that takes a shared one, --db postgresql://...")
            if self.port == 0:
                raise RelayError("--workers N shares one port among the workers: give it, --port P")

    @property
    def udp_port(self) -> int:
        """The UDP clock exchange's port as asked for (the HTTP port's number unless given)."""
        return self.port if self.clock_port is None else self.clock_port

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> RelayConfig:
        """The configuration ``dcuscope relay``'s options give (:func:`~dcuscope.relay.commands.add_relay_arguments`);
        RelayError names the option at fault."""
        try:
            limits = Limits().with_values(args.limit)
        except ValueError as exc:
            raise RelayError(f"--limit: {exc}") from None
        try:
            trusted = TrustedProxies.parse(args.trusted_proxy)
        except ValueError as exc:
            raise RelayError(f"--trusted-proxy: {exc}") from None
        if args.redis is None and args.redis_ca is not None:
            raise RelayError("--redis-ca needs --redis rediss://...")
        frame_limits = FrameLimits.parse(args.frame_limit)
        from dcuscope.relay.api.fanout import check_url  # aiohttp and socketio: not before the command runs

        return cls(
            db=args.db, host=args.host, port=args.port, clock_port=args.clock_port, clock=args.clock,
            credentials=Credentials.from_files(args.token, args.viewer_tokens, args.node_tokens),
            limits=limits, push_hz=DEFAULT_PUSH_HZ if args.push_hz is None else args.push_hz,
            allow_hosts=tuple(args.allow_host), frame_limits=frame_limits, otlp=_otlp(args, frame_limits),
            trusted_proxies=trusted, redis=None if args.redis is None else check_url(args.redis, args.redis_ca),
            name=args.name, compact_after_s=args.compact_after, tls=_tls(args), store_timeout_s=args.store_timeout,
            retention=parse_retention(args.retain) if args.retain is not None else None,
            workers=args.workers, reuse_port=args.reuse_port, log_level=args.log_level)


def _tls(args: argparse.Namespace) -> ServerTls | None:
    if not (args.tls_cert or args.tls_key or args.tls_client_ca):
        return None
    if not (args.tls_cert and args.tls_key):
        raise RelayError("--tls-cert and --tls-key go together (--tls-client-ca needs both)")
    return ServerTls(args.tls_cert, args.tls_key, args.tls_client_ca)


def _otlp(args: argparse.Namespace, frame_limits: FrameLimits) -> OtlpConfig | None:
    options = {"--otlp-every": args.otlp_every, "--otlp-queue": args.otlp_queue, "--otlp-timeout": args.otlp_timeout,
               "--otlp-ca": args.otlp_ca}
    if args.otlp is None:
        given = [name for name, value in options.items() if value is not None]
        if given:
            raise RelayError(f"{given[0]} needs --otlp URL")
        return None
    has_limit = frame_limits.default_ns is not None or bool(frame_limits.per_node_ns)
    return otlp_config(args.otlp, DEFAULT_EVERY if args.otlp_every is None else args.otlp_every,
                       DEFAULT_QUEUE if args.otlp_queue is None else args.otlp_queue,
                       DEFAULT_TIMEOUT_S if args.otlp_timeout is None else args.otlp_timeout, has_limit, args.otlp_ca)
