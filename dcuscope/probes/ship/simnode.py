"""A simulated node: synthetic probe events of a multi-camera pipeline, shipped to a relay.

For tests and benchmarks of the relay where a real pipeline is not the point (and as the
stand-in a real ``dcuscope run --probes --relay`` process replaces at integration). Events
follow the shape the tracer produces: one origin per frame at the source's framestamp stage,
enter/exit at mux, infer, tiler, convert, osd, enter at the sink; a fraction of frames is
dropped midway (incomplete). Timestamps are true times moved by ``--clock-offset-ns`` and
``--clock-drift-ppm`` (:class:`dcuscope.core.clocks.PretendClock`), as on a node whose clock is off by that
much and runs that much fast; its clock exchanges with the relay read the same pretend clock.

``python -m dcuscope.probes.ship.simnode --relay URL --node NAME [--paced] ...`` writes the events it shipped
to ``--out`` (.npz with the header) so a test can compute ``node_stats`` over exactly them.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

import numpy as np

from dcuscope.core.clocks import PretendClock
from dcuscope.probes.clocks.sysclock import DEFAULT_UDS
from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.probes.ship.nodetls import add_tls_arguments, tls_from_args
from dcuscope.probes.ship.relayexport import RelayExporter
from dcuscope.probes.ship.spoolargs import add_spool_arguments, spool_from_args
from dcuscope.protocol.credentials import NODE_TOKEN_HELP, add_token_argument
from dcuscope.protocol.events import ENTER, EVENT_DTYPE, EXIT, ORIGIN, TraceHeader

STAGES = ("mux", "infer", "tiler", "convert", "osd")
STAGE_MEAN_NS = (2_000_000, 30_000_000, 3_000_000, 1_000_000, 4_000_000)
EVENTS_PER_FRAME = 2 + 2 * len(STAGES)


def header_for(node: str, sources: int, started_ns: int = 0) -> TraceHeader:
    stages = [f"src{k}" for k in range(sources)] + list(STAGES) + ["sink"]
    kinds = {**{f"src{k}": "framestamp" for k in range(sources)}, **{s: s for s in STAGES}, "sink": "fakesink"}
    return TraceHeader(node=node, clock="realtime", stages=stages, kinds=kinds,
                       sources={k: f"sim://camera{k}" for k in range(sources)}, started_ns=started_ns)


def synth_events(n_frames: int, sources: int, fps: float, t0_ns: int, *, drop_rate: float = 0.0,
                 seed: int = 0, first_frame: int = 0) -> np.ndarray:
    """Events of frames ``first_frame..first_frame+n_frames`` of each source, sorted by time."""
    rng = np.random.default_rng(seed + first_frame)
    period = int(1e9 / fps)
    src = np.repeat(np.arange(sources, dtype=np.int32), n_frames)
    frame = np.tile(np.arange(first_frame, first_frame + n_frames, dtype=np.int64), sources)
    n = len(src)
    origin = t0_ns + frame * period + src.astype(np.int64) * (period // max(sources, 1))
    delays = (np.asarray(STAGE_MEAN_NS)[None, :] * rng.uniform(0.6, 1.6, (n, len(STAGES)))).astype(np.int64)
    gaps = rng.integers(20_000, 400_000, (n, len(STAGES) + 1))
    # A dropped frame stops after a random stage: it never reaches the sink.
    stop = np.where(rng.random(n) < drop_rate, rng.integers(0, len(STAGES), n), len(STAGES) + 1)
    parts = [_events(origin, src, frame, src.astype(np.int64), ORIGIN)]
    t = origin
    for j in range(len(STAGES)):
        t_in = t + gaps[:, j]
        t_out = t_in + delays[:, j]
        alive_in, alive_out = stop > j, stop > j + 1
        parts.append(_events(t_in[alive_in], src[alive_in], frame[alive_in], sources + j, ENTER))
        parts.append(_events(t_out[alive_out], src[alive_out], frame[alive_out], sources + j, EXIT))
        t = t_out
    sink = stop > len(STAGES)
    parts.append(_events((t + gaps[:, -1])[sink], src[sink], frame[sink], sources + len(STAGES), ENTER))
    events = np.concatenate(parts)
    return events[np.argsort(events["ts"], kind="stable")]


def _events(ts, source, frame, stage, point) -> np.ndarray:
    ev = np.zeros(len(ts), EVENT_DTYPE)
    ev["ts"], ev["source"], ev["frame"], ev["stage"], ev["point"] = ts, source, frame, stage, point
    return ev


def feed(exporter: RelayExporter, events: np.ndarray, *, paced: bool, clock: PretendClock | None = None,
         tick_s: float = 0.01, max_buffered: int = 200_000, chunk: int = 4096,
         stop: threading.Event | None = None) -> int:
    """Write ``events`` (node-clock times: ``clock``'s): paced, each once its time came, until ``stop``
    is set; else as fast as the exporter's buffer drains (throughput tests). Returns how many were written."""
    clock = clock or PretendClock()
    if paced:
        i = 0
        while i < len(events) and not (stop is not None and stop.is_set()):
            now = clock.now()
            j = int(np.searchsorted(events["ts"], now, side="right"))
            if j > i:
                exporter.write(events[i:j])
                i = j
            # Until the next event is due (at least a tick: events closer than that go together): a slow
            # node wakes for its events, not 1/tick_s times a second.
            due_s = (int(events["ts"][i]) - clock.now()) / 1e9 if i < len(events) else 0.0
            time.sleep(max(tick_s, due_s) if stop is None else min(max(tick_s, due_s), 0.1))
        return i
    # Held back while the exporter's buffer is full; with a spool, only while events wait to be cut (the
    # spool takes every batch, the memory bound sends the oldest to disk only).
    held = "pending" if exporter.counters()["spooled"] is not None else "buffered"
    for i in range(0, len(events), chunk):
        while exporter.counters()[held] > max_buffered:
            time.sleep(0.002)
        exporter.write(events[i:i + chunk])
    return len(events)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m dcuscope.probes.ship.simnode", description=__doc__.splitlines()[0],
        epilog=f"Exit status: 0 every event acknowledged by a relay, {UNACKNOWLEDGED_STATUS} not (the JSON line on "
               "stdout counts them), 2 bad arguments.")
    p.add_argument("--relay", required=True)
    p.add_argument("--node", required=True)
    add_token_argument(p, NODE_TOKEN_HELP)
    add_tls_arguments(p)
    p.add_argument("--sources", type=int, default=2)
    p.add_argument("--fps", type=float, default=25.0, help="frames per second per source")
    p.add_argument("--frames", type=int, default=100, help="frames per source")
    p.add_argument("--t0-ns", type=int, default=0, help="true time of frame 0 (default: now + 0.2 s)")
    p.add_argument("--clock-offset-ns", type=int, default=0, help="testing aid: the node's clock is off by this much")
    p.add_argument("--clock-drift-ppm", type=float, default=0.0,
                   help="testing aid: the node's clock runs this many ppm fast (negative: slow) from the start")
    p.add_argument("--clock-start-ns", type=int, default=-1,
                   help="CLOCK_REALTIME the drift counts from (default: when the node starts)")
    p.add_argument("--drop-rate", type=float, default=0.0)
    p.add_argument("--paced", action="store_true", help="write each event when its time comes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch-events", type=int, default=8192)
    p.add_argument("--flush-interval", type=float, default=0.05,
                   help="the longest an event waits on the node to be cut into a batch (--fixed-flush: the period)")
    p.add_argument("--fixed-flush", action="store_true",
                   help="cut batches every --flush-interval or at --batch-events, not as soon as the link is idle "
                        "(the behaviour before adaptive batching, for side-by-side benchmarks)")
    p.add_argument("--max-buffer-events", type=int, default=2_000_000)
    p.add_argument("--close-timeout", type=float, default=30.0, metavar="S",
                   help="at the end, keep trying every --relay for up to S seconds until all is acknowledged "
                        "(default 30)")
    p.add_argument("--ptp-socket", default=DEFAULT_UDS, help=f"the local ptp4l's UDS, read with pmc (default {DEFAULT_UDS})")
    add_spool_arguments(p)
    p.add_argument("--out", help="write header and shipped events here (.npz)")
    p.add_argument("--linger", action="store_true",
                   help="after the last event, keep the run open (connected, not ended) until standard input closes")
    p.add_argument("--until-stdin-closes", action="store_true",
                   help="with --paced: stop writing events when standard input closes (a test ends the run when "
                        "its check is done); --out holds those written")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    tls = tls_from_args(args)

    pretend = PretendClock(args.clock_offset_ns, args.clock_drift_ppm, start_ns=args.clock_start_ns)
    t0 = args.t0_ns or time.clock_gettime_ns(time.CLOCK_REALTIME) + 200_000_000
    events = synth_events(args.frames, args.sources, args.fps, t0, drop_rate=args.drop_rate, seed=args.seed)
    events["ts"] = pretend.shift(events["ts"])
    header = header_for(args.node, args.sources, pretend.of(t0))
    exporter = RelayExporter(args.relay, args.node, token=args.token, pretend=pretend,
                             batch_events=args.batch_events, flush_interval_s=args.flush_interval,
                             adaptive=not args.fixed_flush,
                             max_buffer_events=args.max_buffer_events, close_timeout_s=args.close_timeout,
                             ptp_socket=args.ptp_socket, tls=tls,
                             spool=spool_from_args(args, relay=args.relay, token=args.token, tls=tls))
    started = time.monotonic()
    exporter.start(header)
    stop = None
    if args.until_stdin_closes:
        stop = threading.Event()
        threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    events = events[:feed(exporter, events, paced=args.paced, clock=pretend, stop=stop)]
    if args.linger:
        sys.stdin.read()  # a test holds the run live for as long as its check needs, then closes our stdin
    exporter.close(dropped=0)
    if args.out:
        np.savez(args.out, events=events, header=json.dumps(header.to_dict()))
    print(json.dumps(dict(exporter.counters(), events=len(events), seconds=time.monotonic() - started)), flush=True)
    delivery = exporter.delivery()
    print(f"simnode {args.node}: {delivery.line()}", file=sys.stderr, flush=True)
    return 0 if delivery.complete else UNACKNOWLEDGED_STATUS


if __name__ == "__main__":
    sys.exit(main())
