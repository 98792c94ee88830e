"""The figures of one stream count, from its run's trace, with 95 % intervals.

The first ``warmup`` seconds of frames are left out (model load, the first batches, caches).
Intervals come from :mod:`dcuscope.model.bootstrap`, as compare's do: the frames of a run are
resampled in blocks of consecutive frames, so that their correlation is kept.

- Frames/s per stream: for each stream, 1 / the mean gap between the origins of its frames that
  reached the sink; its interval from the gaps' block bootstrap, in blocks of at least a second
  (:func:`slowest_stream_fps`). The stream that keeps the
  smallest share of its nominal rate is what a floor is checked against (every camera must keep
  its rate); the mean over the streams is the paper's figure.
- End to end: the frame delay (origin to sink) of complete frames: mean (the paper's A = S/n),
  p50, p95, p99, each with its interval.
- Each stage's mean delay, service and wait (delay = service + wait), and utilization (busy
  fraction of the run); the limiting stage (:func:`dcuscope.model.delays.bottleneck`).
- Frames dropped after the warm-up, by reason, and frames lost before the mux (not those still
  queued when the run was ended: the search ends it, not the pipeline).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from dcuscope.model.bootstrap import block_length, interval, resample
from dcuscope.model.compare import E2E, time_series
from dcuscope.model.delays import delay_stats, frame_delays
from dcuscope.model.facts import Accounting
from dcuscope.model.frametable import frame_table
from dcuscope.probes.trace.tracefile import Trace
from dcuscope.protocol.events import FACT, ORIGIN

QUANTILES = (50, 95, 99)
FIGURES = ("mean",) + tuple(f"p{q}" for q in QUANTILES)
RESAMPLES = 1000
LEVEL = 0.95
NOT_DROPS = {"stopped"}
"""Drop reasons that are not the pipeline's: frames still queued when the run was ended."""


def after_warmup(events: np.ndarray, warmup_s: float) -> np.ndarray:
    """The events of the frames that originated ``warmup_s`` or more after the first origin, and
    every fact (which thread pushes each stage, each source's nominal rate: sent when they change,
    mostly at the start)."""
    origins = events[events["point"] == ORIGIN]
    if len(origins) == 0 or warmup_s <= 0:
        return events
    cutoff = int(origins["ts"].min()) + int(warmup_s * 1e9)
    late = origins[origins["ts"] >= cutoff]
    keys = (events["source"].astype(np.int64) << 40) | events["frame"].astype(np.int64)
    keep = (late["source"].astype(np.int64) << 40) | late["frame"].astype(np.int64)
    return events[np.isin(keys, keep) | (events["point"] == FACT)]


@dataclass
class Estimate:
    value: float
    low: float
    high: float


@dataclass
class CountFigures:
    """One stream count's figures (module docstring); ms unless said."""

    streams: int
    frames: int
    incomplete: int
    fps: Estimate | None
    """The frames/s of the stream furthest below its rate, with its interval; None when a stream
    brought fewer than 3 frames through."""
    fps_mean: float
    """Mean over the streams of their frames/s."""
    nominal_fps: float | None
    """That stream's nominal rate (its caps'); None when its source said none."""
    e2e: dict[str, Estimate]
    """FIGURES -> the frame delay's figure; empty without complete frames."""
    stages: dict[str, dict]
    """Stage -> {delay, service, wait (mean ms, None without them), utilization (0-1 or None)}."""
    between_ms: float | None
    """A minus the sum of the stage delays: hand-overs and queues between stages."""
    limiting: dict | None
    """{stage, utilization, thread_utilization, saturated} of the bottleneck."""
    threads: dict[str, int] = field(default_factory=dict)
    """Stage -> the streaming thread that pushes its output (stages on one thread share its time)."""
    dropped: dict[str, int] = field(default_factory=dict)
    """Reason -> frames dropped after the warm-up, over every stream."""
    delivered: int = 0
    series: dict[tuple[str, str], np.ndarray] = field(default_factory=dict, repr=False)
    """(stage or e2e, kind) -> ms per complete frame in origin order (for bounds on any stage)."""

    def to_json(self) -> dict:
        out = asdict(self)
        out.pop("series")
        return out


def measure(trace: Trace, streams: int, warmup_s: float, seed: int = 0, resamples: int = RESAMPLES) -> CountFigures:
    events = after_warmup(trace.events, warmup_s)
    accounting = Accounting(trace.header.stages)
    accounting.add(events)
    fd = frame_delays(frame_table(trace.header, events))
    stats = delay_stats(fd, trace.header.sources, trace.dropped, accounting)
    rng = np.random.default_rng(seed)
    series = time_series(fd)
    e2e = {}
    if fd.chains.complete.sum() >= 2:
        r = resample(series[(E2E, "delay")], rng, resamples, quantiles=QUANTILES)
        e2e = {f: Estimate(r.estimate[f], *interval(r, f, LEVEL)) for f in FIGURES}
    fps, nominal = slowest_stream_fps(fd, stats["sources"], rng, resamples)
    stages = {name: {"delay": st["mean_ms"], "service": st["service"]["mean_ms"] if st["service"]["count"] else None,
                     "wait": st["wait"]["mean_ms"] if st["wait"]["count"] else None,
                     "utilization": st["utilization"]}
              for name, st in stats["stages"].items()}
    a_ms = stats["frame"]["mean_ms"]
    delays = [st["delay"] for st in stages.values() if st["delay"] is not None]
    neck = stats["bottleneck"]
    dropped: dict[str, int] = {}
    for src in stats["sources"].values():
        for reason, n in src["dropped"].items():
            if reason in NOT_DROPS:
                continue
            dropped[reason] = dropped.get(reason, 0) + n
        for reason in ("lost_upstream", "decoder_dropped"):
            if src[reason]:
                dropped[reason] = dropped.get(reason, 0) + src[reason]
    return CountFigures(
        streams=streams, frames=stats["frames"]["complete"], incomplete=stats["frames"]["incomplete"],
        fps=fps,
        fps_mean=float(np.mean(list(stats["fps"].values()))) if stats["fps"] else 0.0,
        nominal_fps=nominal, e2e=e2e, stages=stages,
        between_ms=a_ms - sum(delays) if a_ms is not None else None,
        limiting={k: neck[k] for k in ("stage", "utilization", "thread_utilization", "saturated")} if neck else None,
        threads=accounting.threads(), dropped=dropped, delivered=sum(s["delivered"] for s in stats["sources"].values()), series=series)


def slowest_stream_fps(fd, sources: dict[str, dict], rng: np.random.Generator,
                       resamples: int) -> tuple[Estimate | None, float | None]:
    """(frames/s, nominal rate) of the stream that keeps the smallest share of its nominal rate (of
    the fewest frames/s when rates are unknown), with its interval; (None, its rate) when a stream
    brought fewer than 3 frames through.

    The rate is (n - 1) / the span of the stream's n complete frames, i.e. 1 / their mean gap; its
    interval is that of 1 / the mean gap by the block bootstrap, in blocks of at least a second of
    frames. A live stream that comes in bursts (a jitter buffer, a batch) at a steady rate has
    gaps that swing widely, short after long: blocks shorter than a burst would take that swing
    for uncertainty, while a second's gaps add up to about a second."""
    table, complete = fd.table, fd.chains.complete
    worst = None
    for sid in sorted(int(s) for s in sources):
        nominal = sources[str(sid)]["nominal_fps"]
        origin = np.sort(table.origin[complete & (table.source == sid)]).astype(np.float64)
        if len(origin) < 3 or origin[-1] == origin[0]:
            return None, nominal
        gaps = np.diff(origin) / 1e9
        fps = 1.0 / gaps.mean()
        share = fps / nominal if nominal else fps
        if worst is None or share < worst[0]:
            worst = (share, fps, gaps, nominal)
    if worst is None:
        return None, None
    _, fps, gaps, nominal = worst
    block = min(max(block_length(gaps), math.ceil(fps)), max(1, len(gaps) // 3))
    low_gap, high_gap = interval(resample(gaps, rng, resamples, block=block), "mean", LEVEL)
    return Estimate(fps, 1.0 / high_gap, 1.0 / low_gap), nominal


def stage_estimate(figures: CountFigures, stage: str, kind: str, figure: str, seed: int = 0,
                   resamples: int = RESAMPLES) -> Estimate | None:
    """A bound's figure of any stage (``infer.service.p99``) with its interval; None if the run has none."""
    if stage == E2E and kind == "delay" and figure in figures.e2e:
        return figures.e2e[figure]
    x = figures.series.get((stage, kind))
    if x is None or len(x) < 2:
        return None
    q = int(figure[1:]) if figure != "mean" else None
    r = resample(x, np.random.default_rng(seed), resamples, quantiles=(q,) if q else QUANTILES)
    return Estimate(r.estimate[figure], *interval(r, figure, LEVEL))
