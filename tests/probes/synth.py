"""Synthetic probe events of a known pipeline run, built from explicit timestamp matrices.

The generator fixes every frame's enter/exit timestamps first (``Truth``) and only then turns
them into events, so tests can compare statistics against values computed independently from
the matrices. Vectorised: the benchmark uses it for a million events.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dcuscope.protocol.events import CAPTURE, DROP, ENTER, EVENT_DTYPE, EXIT, FACT, FACT_NOMINAL_MHZ, FACT_THREAD, ORIGIN, READY, TraceHeader

STAGES = ("mux", "infer", "tiler", "convert", "osd")
T0 = 1_700_000_000_000_000_000  # a realistic CLOCK_REALTIME value, ns


@dataclass
class Truth:
    """Per frame (row, ordered by source then frame) and per processing stage (column)."""

    source: np.ndarray
    frame: np.ndarray
    origin: np.ndarray
    enter: np.ndarray
    """(frames, len(STAGES) + 1): the processing stages, then the sink."""
    exit: np.ndarray
    """(frames, len(STAGES)): no exit at the sink."""


def pipeline_run(
    n_frames: int,
    n_sources: int = 2,
    *,
    period_ns: int = 100_000_000,
    stage_ns=(2_000_000, 30_000_000, 3_000_000, 1_000_000, 4_000_000),
    gap_ns: int = 50_000,
    jitter_ns: int = 0,
    batched_mux: bool = False,
    node: str = "dcu1",
    seed: int = 0,
) -> tuple[TraceHeader, np.ndarray, Truth]:
    """Events of ``n_frames`` frames from each of ``n_sources`` sources through STAGES + sink.

    Each stage delay is ``stage_ns[j]`` plus uniform jitter in [0, jitter_ns]; each gap is
    ``gap_ns`` plus jitter. With ``batched_mux`` all sources' frame i leave the mux at one
    timestamp, like a real batch. Events come back shuffled: order must not matter.
    """
    rng = np.random.default_rng(seed)
    n_stages = len(STAGES)
    source = np.repeat(np.arange(n_sources, dtype=np.int32), n_frames)
    frame = np.tile(np.arange(n_frames, dtype=np.int64), n_sources)
    total = len(source)
    origin = T0 + frame * period_ns + source.astype(np.int64) * 1_000_000

    def jitter(shape):
        return rng.integers(0, jitter_ns + 1, shape) if jitter_ns else np.zeros(shape, np.int64)

    delays = np.asarray(stage_ns, np.int64)[None, :] + jitter((total, n_stages))
    gaps = gap_ns + jitter((total, n_stages + 1))
    enter = np.zeros((total, n_stages + 1), np.int64)
    exit_ = np.zeros((total, n_stages), np.int64)
    out = origin
    for j in range(n_stages):
        enter[:, j] = out + gaps[:, j]
        exit_[:, j] = enter[:, j] + delays[:, j]
        if j == 0 and batched_mux:
            exit_[:, 0] = exit_[:, 0].reshape(n_sources, n_frames).max(axis=0)[frame]
        out = exit_[:, j]
    enter[:, n_stages] = out + gaps[:, n_stages]

    header = TraceHeader(
        node=node, clock="realtime",
        stages=[f"src{k}" for k in range(n_sources)] + list(STAGES) + ["sink"],
        sources={k: f"file:///clip{k}.avi" for k in range(n_sources)}, started_ns=T0,
    )
    first = n_sources  # stage index of STAGES[0]
    parts = [_events(origin, source, frame, source.astype(np.int16), ORIGIN)]
    for j in range(n_stages):
        parts.append(_events(enter[:, j], source, frame, first + j, ENTER))
        parts.append(_events(exit_[:, j], source, frame, first + j, EXIT))
    parts.append(_events(enter[:, n_stages], source, frame, first + n_stages, ENTER))
    parts += _format2_events(np.random.default_rng(seed + 1), source, frame, origin, enter, exit_, first,
                             n_sources if batched_mux else 1)
    events = np.concatenate(parts)
    events = events[rng.permutation(len(events))]
    return header, events, Truth(source, frame, origin, enter, exit_)


def troubled_run(seed: int, n_frames: int = 130, node: str = "dcu1") -> tuple[TraceHeader, np.ndarray, int, int]:
    """A run with every kind of trouble, its events in the order a relay would receive them.

    From a :func:`pipeline_run` (random sources, jitter, batching): frames dropped midway
    (they never reach the sink), single events lost, tracepoints seen twice (a later copy),
    events reordered by up to 30 ms, and, at the very end, late copies of tracepoints of
    frames long finished (timestamps a little later than the originals, so that the earliest
    kept is the original wherever the copy lands). 130 frames at 10/s span 13 s: more than
    the relay's 10 s window and settle time. Returns (header, events, number of late copies at
    the end of events, dropped event count).
    """
    rng = np.random.default_rng(seed)
    n_sources = int(rng.integers(1, 4))
    header, events, _ = pipeline_run(n_frames, n_sources, jitter_ns=int(rng.integers(1, 20_000_000)),
                                     batched_mux=bool(rng.integers(2)), node=node, seed=seed)
    n = n_sources * n_frames
    facts = events[events["point"] == FACT]
    events = events[events["point"] != FACT]
    row = events["source"].astype(np.int64) * n_frames + events["frame"]
    # Dropped midway: the frame stops at a random stage, half of them after entering it.
    frame_cut = np.where(rng.random(n) < 0.1, rng.integers(n_sources, len(header.stages), n), len(header.stages))
    cut = frame_cut[row]
    entered_only = (rng.random(n) < 0.5)[row]
    past = (events["stage"] > cut) | ((events["stage"] == cut) & (events["point"] == EXIT) & entered_only)
    events = events[~past & (rng.random(len(events)) >= 0.01)]  # and 1 % of single events lost
    cut_rows = np.flatnonzero(frame_cut < len(header.stages))
    drops = _events(T0 + (cut_rows % n_frames) * 100_000_000 + 50_000_000, cut_rows // n_frames,
                    cut_rows % n_frames, frame_cut[cut_rows], DROP, 1)
    events = np.concatenate([facts, events, drops])
    copies = events[rng.random(len(events)) < 0.02].copy()
    copies["ts"] += rng.integers(0, 1_000_000, len(copies))
    events = np.concatenate([events, copies])
    events = events[np.argsort(events["ts"] + rng.integers(0, 30_000_000, len(events)), kind="stable")]
    early = events[(events["ts"] < T0 + (n_frames // 3) * 100_000_000) & (rng.random(len(events)) < 0.05)].copy()
    early["ts"] += rng.integers(0, 1000, len(early))
    return header, np.concatenate([events, early]), len(early), int(rng.integers(0, 50))


def _format2_events(rng, source, frame, origin, enter, exit_, first, mux_group) -> list[np.ndarray]:
    """Ready points (each stage waits a random part of its delay; a batched mux is ready when
    the last frame of the batch entered), capture points for source 0, facts (a thread per
    stage, the nominal rate per source)."""
    parts = []
    for j in range(exit_.shape[1]):
        ready = enter[:, j] + (rng.random(len(frame)) * 0.5 * (exit_[:, j] - enter[:, j])).astype(np.int64)
        code = np.ones(len(frame), np.int8)
        if j == 0 and mux_group > 1:
            ready = enter[:, 0].reshape(mux_group, -1).max(axis=0)[frame]
            code = np.where(source == 0, mux_group, -mux_group).astype(np.int8)
        parts.append(_events(ready, source, frame, first + j, READY, code))
    cam = source == 0
    parts.append(_events(origin[cam] - 5_000_000, source[cam], frame[cam], source[cam], CAPTURE))
    stages = np.arange(first, first + exit_.shape[1], dtype=np.int64)
    parts.append(_events(np.full(len(stages), T0), 0, np.where(stages < first + 2, 1, 2), stages, FACT, FACT_THREAD))
    ids = np.unique(source)
    parts.append(_events(np.full(len(ids), T0), ids, 10_000, ids, FACT, FACT_NOMINAL_MHZ))
    return parts


def _events(ts, source, frame, stage, point, code=0) -> np.ndarray:
    ev = np.zeros(len(ts), EVENT_DTYPE)
    ev["ts"], ev["source"], ev["frame"], ev["stage"], ev["point"], ev["code"] = ts, source, frame, stage, point, code
    return ev


def run_commands(*argv: str) -> tuple[int, str, str]:
    """Run ``dcuscope stats|export ARGV`` in-process: (exit code, stdout, stderr)."""
    import argparse
    import contextlib
    import io

    from dcuscope.commands.export import add_export_parser
    from dcuscope.commands.stats import add_stats_parser

    parser = argparse.ArgumentParser(prog="dcuscope")
    sub = parser.add_subparsers()
    add_stats_parser(sub)
    add_export_parser(sub)
    args = parser.parse_args(list(argv))
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = args.func(args)
    return rc, out.getvalue(), err.getvalue()
