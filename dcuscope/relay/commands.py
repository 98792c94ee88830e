"""``dcuscope relay``: argparse wiring (``add_relay_parser``), used by ``dcuscope/cli.py``."""

from __future__ import annotations

import argparse
import logging
import sys

from dcuscope.core.ports import check_port_free
from dcuscope.protocol.credentials import TOKEN_ENV, add_token_argument
from dcuscope.relay.clock.correction import CLOCK_MODES
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.export.otlpconfig import DEFAULT_EVERY, DEFAULT_QUEUE, DEFAULT_TIMEOUT_S
from dcuscope.relay.guard.limits import limits_help
from dcuscope.relay.store.base import STORE_TIMEOUT_S
from dcuscope.relay.store.compaction import COMPACT_AFTER_S
from dcuscope.relay.workers import run_workers

def add_relay_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``relay`` subcommand; its ``func`` default runs it (returns the exit status)."""
    p = subparsers.add_parser(
        "relay", help="run the monitoring host: ingest from nodes, live delays, storage, API and UI",
        description="Receive probe events from dcuscope nodes (dcuscope run ... --relay URL), estimate "
                    "their clock offsets, compute per-stage and per-frame delays live, store every "
                    "session (SQLite, or PostgreSQL shared by many relays) and serve the HTTP API and the UI.",
        epilog=limits_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    add_relay_arguments(p)
    p.set_defaults(func=run_relay, holds_signals=True)
    return p


def add_relay_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default: loopback only)")
    p.add_argument("--port", type=int, default=3000, help="TCP port (default 3000; 0 picks a free one)")
    p.add_argument("--clock-port", type=int, metavar="N",
                   help="UDP port of the light clock exchange nodes use beside their WebSocket (kernel "
                        "timestamps, tighter offset estimates); default: the same number as --port; 0 turns it "
                        "off (nodes then exchange over the WebSocket)")
    p.add_argument("--db", default="dcuscope.db", metavar="FILE|URL",
                   help="where sessions are stored: an SQLite file (one relay; default ./dcuscope.db) or a PostgreSQL "
                        "database, postgresql://USER[:PASSWORD]@HOST[:PORT]/DB, shared by any number of relays: any "
                        "relay takes any node, and a node whose relay died resumes its run on another (README, Fleet); "
                        "postgresql://H1:5432,H2:5432/DB?target_session_attrs=read-write follows whichever host is "
                        "the primary (docs/store-failover.md)")
    p.add_argument("--store-timeout", type=float, default=STORE_TIMEOUT_S, metavar="SECONDS",
                   help="a PostgreSQL store's write not answered within this long is cancelled, and its node told to "
                        "send it again (nothing is stored twice): a relay never hangs on its store, e.g. on commits "
                        "waiting for a synchronous standby that is gone (/api/health and /metrics say so; "
                        f"docs/store-failover.md) (default {STORE_TIMEOUT_S:g})")
    p.add_argument("--workers", type=int, default=1, metavar="N",
                   help="run N relay processes on this host sharing --port (SO_REUSEPORT) and the --db PostgreSQL "
                        "store: N cores for ingest; each answers UDP clock exchanges on the clock port + its index "
                        "(default 1)")
    p.add_argument("--reuse-port", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--retain", metavar="raw=7d,rollups=400d",
                   help="what the store keeps: raw=TIME deletes whole sessions last heard from longer ago, "
                        "rollups=TIME the minute and hour rollups (what `dcuscope stats --node --since` and the "
                        "page's history read) older than that; DAYS alone is raw=DAYS. Checked every minute, deleted "
                        "in small parts that do not hold ingest up (default: keep everything)")
    p.add_argument("--compact-after", type=float, default=COMPACT_AFTER_S, metavar="SECONDS",
                   help="move batches stored this long into compact segments (about 3.5 bytes an event instead of "
                        f"24-32; read as before by every reader), in a process of its own beside the relay (default {COMPACT_AFTER_S:g}; "
                        "0: never, e.g. when `dcuscope db compact` runs elsewhere)")
    add_token_argument(p, f"the admin's secret: it may do everything (read the page, the API and /metrics, and stream "
                        f"as any node). Once --token or --viewer-tokens is given, nothing but the page's shell "
                        f"answers without a credential (default ${TOKEN_ENV})")
    p.add_argument("--viewer-tokens", metavar="FILE",
                   help="read-only credentials: a file of 'NAME TOKEN' lines; a viewer may read the page, GET "
                        "/api/* and /metrics, and never stream")
    p.add_argument("--node-tokens", metavar="FILE",
                   help="per-node credentials: a file of 'NODE TOKEN' lines; a node presenting its own token "
                        "may stream under its own name only, and read nothing (beside --token, which lets a node "
                        "use any name)")
    p.add_argument("--tls-cert", metavar="FILE",
                   help="serve the page, the API, /metrics and the nodes' WebSocket over HTTPS/WSS only, with this "
                        "certificate (PEM, its chain after it); SIGHUP rereads it and --tls-key (renewals need no "
                        "restart: new connections get the new one; a file that cannot be loaded keeps the old)")
    p.add_argument("--tls-key", metavar="FILE", help="the private key of --tls-cert (PEM)")
    p.add_argument("--tls-client-ca", metavar="FILE",
                   help="with --tls-cert: nodes must present a certificate this CA (PEM) signed, and stream under "
                        "the name it gives (its first DNS subjectAltName, else its CN) only; browsers need none")
    p.add_argument("--clock", choices=CLOCK_MODES, default="auto",
                   help="ptp: never correct node timestamps; estimate: subtract each node's estimated "
                        "offset; auto: trust PTP where the node reports it locked and its system clock following it, "
                        "else estimate and say why (default auto)")
    p.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                   help="without --token, also answer requests (Host and browser Origin) naming this host "
                        "(repeatable); by default only IP addresses and localhost, against DNS rebinding "
                        "(nodes may use any name)")
    p.add_argument("--trusted-proxy", action="append", default=[], metavar="ADDR[,ADDR...]",
                   help="behind a TCP load balancer or proxy: the proxies' IP addresses or networks (CIDR, e.g. "
                        "10.0.0.0/24; repeatable or comma-separated). Their connections must start with a PROXY "
                        "protocol header (v1 or v2, HAProxy send-proxy, nginx proxy_protocol): the relay takes the "
                        "client's address from it, for connections_per_peer and request addresses, and closes "
                        "those without a valid one. Other peers' headers are never read (default: none)")
    p.add_argument("--limit", action="append", default=[], metavar="NAME=VALUE",
                   help="change one of the bounds listed below (repeatable), e.g. --limit connections_per_peer=64; "
                        "by default each has the default given there")
    p.add_argument("--frame-limit", action="append", default=[], metavar="[NODE=]MS",
                   help="the longest a frame may take (origin to the end of its chain) on every node (MS) or on one "
                        "(NODE=MS, repeatable): exported in /metrics for the shipped alert rule "
                        "(configs/prometheus/), and frames over it are always sent with --otlp (default: no limit)")
    p.add_argument("--otlp", metavar="URL",
                   help="send frames as OpenTelemetry traces to this OTLP/HTTP endpoint (an OpenTelemetry Collector, "
                        "Jaeger, Tempo), e.g. http://127.0.0.1:4318/v1/traces (no path: /v1/traces): one trace per "
                        "frame, a span per stage (wait, service) and per gap; 1 in --otlp-every frames plus every "
                        "frame over its --frame-limit (default: no export)")
    p.add_argument("--otlp-every", type=int, metavar="N",
                   help=f"with --otlp: send 1 in N complete frames of each node (default {DEFAULT_EVERY}); 0: only "
                        "frames over their --frame-limit")
    p.add_argument("--otlp-queue", type=int, metavar="N",
                   help=f"with --otlp: frames waiting for export at most (default {DEFAULT_QUEUE}); beyond, frames are "
                        "dropped and counted (dcuscope_otlp_frames_dropped_total), never waited for")
    p.add_argument("--otlp-timeout", type=float, metavar="S",
                   help=f"with --otlp: seconds one export request may take, retries included (default "
                        f"{DEFAULT_TIMEOUT_S:g}); its frames are dropped and counted after it")
    p.add_argument("--otlp-ca", metavar="FILE",
                   help="with --otlp https://...: the CA certificates (PEM) the collector's certificate must come "
                        "from (default: OTEL_EXPORTER_OTLP_CERTIFICATE, REQUESTS_CA_BUNDLE, else certifi's CAs)")
    p.add_argument("--redis", metavar="URL",
                   help="Redis that carries every relay's live pushes to every relay's browsers "
                        "(redis://HOST:PORT/DB; python-socketio's AsyncRedisManager): with relays sharing "
                        "--db postgresql://..., a page on any relay shows every DCU of the fleet live. Redis "
                        "down: ingest and storage go on, other relays' pages catch up when it returns; rediss://: "
                        "over TLS, the server's certificate checked (the system's CAs, or --redis-ca); "
                        "redis+sentinel://S1:26379,S2:26379/DB/SERVICE: Redis Sentinels, the master of SERVICE "
                        "followed through a failover (docs/store-failover.md)")
    p.add_argument("--redis-ca", metavar="FILE",
                   help="with --redis rediss://...: the CA certificates (PEM) the Redis server's certificate must "
                        "come from, instead of the system's (the same as the URL's ssl_ca_certs=FILE)")
    p.add_argument("--name", metavar="NAME",
                   help="how pages and other relays name this relay (default HOST:PORT)")
    p.add_argument("--push-hz", type=float, default=None, metavar="HZ",
                   help="most pushes of a DCU's new frames to browsers per second (default 30; frames go out "
                        "as soon as they are complete, at most this often)")
    p.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="how much the relay logs to stderr: WARNING its failures and warnings, INFO also "
                        "the connections it closes (malformed packets, refused messages), DEBUG everything "
                        "its libraries say (default WARNING)")


def run_relay(args: argparse.Namespace) -> int:
    from dcuscope.relay.server import serve  # aiohttp and socketio load only for this command

    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    config = RelayConfig.from_args(args)
    if config.workers != 1:
        check_port_free(config.host, config.port)
        return run_workers(sys.argv[1:], config.workers, config.udp_port)
    if not config.reuse_port:
        check_port_free(config.host, config.port)
    serve(config)
    return 0
