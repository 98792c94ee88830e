"""The delay model: from a frame table to every delay figure dcuscope reports (vectorised numpy).

``dcuscope stats``, both exports, the relay's live engine, its stored-session API and
``/api/stats`` all derive their figures here, so that they agree exactly. Definitions
(DESIGN.md, after the paper):

- stage delay at stage X = exit - enter of one frame at X (stages without an exit point, such
  as the sink, have none);
- gap A->B = enter at B - exit at A, for consecutive stages A, B (in header order) that the
  frame passed through; at the origin stage the origin timestamp stands for the exit;
- frame delay = end of the frame's chain - origin, the paper's S; the chain ends at the exit of
  the last stage, or at its enter when that stage has no exit point (the sink). So, for every
  complete frame, frame delay = sum of its stage delays + sum of its gaps, exactly.

A frame is *complete* when its chain is unbroken: it has an origin, an enter at every stage it
passed after the origin, an exit (or origin) at every stage before the last, and it reached
the last stage. Only complete frames enter the statistics; the others are counted, never
turned into zero or partial delays. Loops run over stages and sources, never over events.

Three steps, each one function: :func:`frame_delays` (per frame: its chain, its per-stage
columns, its end-to-end delay), :func:`series` (the values the statistics take, of complete
frames) and :func:`delay_summary` (count, mean, percentiles, share, bottleneck). A new
per-stage figure is one more entry of ``FrameDelays.per_stage`` (:data:`STAGE_COLUMNS`): the
CSV, the per-frame JSON and the summaries list it from there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from probes.events import TraceHeader
from probes.frametable import MISSING, FrameTable, frame_table

PERCENTILES = (50, 95, 99)
NS_PER_MS = 1e6
STAGE_COLUMNS = ("delay", "gap")
"""Per-frame, per-stage figures of :class:`FrameDelays` (``per_stage``): ``delay`` = exit -
enter; ``gap`` = enter - exit (or origin) of the previous stage the frame passed."""


@dataclass
class Chains:
    """Each frame's path through the stages, as :func:`chains` derives it from a FrameTable."""

    t_in: np.ndarray
    """(n, n_stages) enter ts, MISSING."""
    t_out: np.ndarray
    """(n, n_stages) exit ts; at the frame's origin stage its origin ts. MISSING."""
    passed: np.ndarray
    """(n, n_stages) bool: the frame has an event at that stage."""
    prev: np.ndarray
    """(n, n_stages) index of the previous stage the frame passed, -1 for none."""
    complete: np.ndarray
    """(n,) bool, see the module docstring."""
    end: np.ndarray
    """(n,) ts where the chain ends (last exit, or the last stage's enter), MISSING."""
    has_exit: np.ndarray
    """(n_stages,) bool: the stage has an exit point (some frame has an exit there)."""


def chains(table: FrameTable, has_exit: np.ndarray | None = None) -> Chains:
    """Derive each frame's chain of stages, its completeness and its end timestamp.

    ``has_exit`` is the one fact that spans frames (whether a stage has an exit point at all):
    taken from the table unless given, so that the relay can judge a few frames by the
    exits its whole run has seen.
    """
    n, n_stages = table.enter.shape
    rows = np.arange(n)
    has_origin = table.origin_stage >= 0
    t_in = table.enter
    t_out = table.exit.copy()
    t_out[rows[has_origin], table.origin_stage[has_origin]] = table.origin[has_origin]
    passed = (t_in != MISSING) | (t_out != MISSING)

    stage_idx = np.arange(n_stages)
    last_upto = np.maximum.accumulate(np.where(passed, stage_idx, -1), axis=1)
    prev = np.full((n, n_stages), -1, np.int64)
    prev[:, 1:] = last_upto[:, :-1]

    if has_exit is None:
        has_exit = (table.exit != MISSING).any(axis=0)
    last = n_stages - 1
    is_origin = stage_idx[None, :] == table.origin_stage[:, None]
    needs_out = passed & ((stage_idx[None, :] < last) | has_exit[None, :])
    broken = (passed & ~is_origin & (t_in == MISSING)).any(axis=1) | (needs_out & (t_out == MISSING)).any(axis=1)
    first_passed = np.where(passed.any(axis=1), passed.argmax(axis=1), -1)
    complete = has_origin & (first_passed == table.origin_stage) & (t_in[:, last] != MISSING) & ~broken

    end = np.where(t_out[:, last] != MISSING, t_out[:, last], t_in[:, last])
    return Chains(t_in=t_in, t_out=t_out, passed=passed, prev=prev, complete=complete, end=end,
                  has_exit=np.asarray(has_exit, bool))


@dataclass
class FrameDelays:
    """Every figure of each frame of a table (rows as the table's), derived once.

    Delays are differences of int64 ns held as float64 ns, NaN where undefined: exact below
    2**53 ns (104 days), and one array type whether a value exists or not.
    """

    table: FrameTable
    chains: Chains
    per_stage: dict[str, np.ndarray]
    """Name (:data:`STAGE_COLUMNS`) -> (n, n_stages) float64 ns, NaN where the frame lacks a
    tracepoint it needs. Defined for incomplete frames too (the exports show them)."""
    delay: np.ndarray
    """(n,) float64 ns: end - origin of each complete frame, NaN for the others."""

    def __len__(self) -> int:
        return len(self.table)


def frame_delays(table: FrameTable, has_exit: np.ndarray | None = None) -> FrameDelays:
    """The chains, per-stage columns and end-to-end delays of every frame of ``table``."""
    ch = chains(table, has_exit)
    n = len(table)
    both = (table.exit != MISSING) & (table.enter != MISSING)
    delay = np.where(both, (table.exit - table.enter).astype(np.float64), np.nan)
    before = ch.t_out[np.arange(n)[:, None], np.maximum(ch.prev, 0)]
    gap_ok = (ch.prev >= 0) & (before != MISSING) & (ch.t_in != MISSING)
    gap = np.where(gap_ok, (ch.t_in - before).astype(np.float64), np.nan)
    end_to_end = np.where(ch.complete, (ch.end - table.origin).astype(np.float64), np.nan)
    return FrameDelays(table=table, chains=ch, per_stage={"delay": delay, "gap": gap}, delay=end_to_end)


@dataclass
class Series:
    """The values the statistics summarise (float64 ns), of complete frames, in table order."""

    stages: dict[str, np.ndarray]
    """Stage with an exit point -> its delays, pipeline order (possibly empty)."""
    gaps: dict[str, np.ndarray]
    """"A->B" -> gaps, in pipeline order of B, then of A."""
    frame: np.ndarray
    """End-to-end delays."""


def series(fd: FrameDelays) -> Series:
    """The stage delays, gaps and frame delays of the complete frames of ``fd``."""
    ch, stages = fd.chains, fd.table.stages
    delay, gap = fd.per_stage["delay"], fd.per_stage["gap"]
    out = Series(stages={}, gaps={}, frame=fd.delay[ch.complete])
    for s, name in enumerate(stages):
        if ch.has_exit[s]:
            out.stages[name] = delay[ch.complete & ~np.isnan(delay[:, s]), s]
    for b, name_b in enumerate(stages):
        ok = ch.complete & ~np.isnan(gap[:, b])
        prev_b = ch.prev[ok, b]
        for a in np.unique(prev_b):
            out.gaps[f"{stages[a]}->{name_b}"] = gap[ok, b][prev_b == a]
    return out


def summarize(values_ms: np.ndarray | Iterable[float]) -> dict:
    """``{count, mean_ms, p50_ms, p95_ms, p99_ms, max_ms}``; values are None when count is 0.

    The mean is that of the values in whole nanoseconds (what timestamps hold), summed exactly
    (float64 adds integers exactly up to 2**53 ns, 104 days in all): so it does not depend on
    the order the values came in, and the relay, which adds finalised and open frames, gets
    the figures of a trace file to the last bit. Sorting would cost 3x the rest.
    """
    values = np.asarray(values_ms, dtype=np.float64).ravel()
    if values.size == 0:
        return {"count": 0, "mean_ms": None, "p50_ms": None, "p95_ms": None, "p99_ms": None, "max_ms": None}
    p50, p95, p99 = np.percentile(values, PERCENTILES, method="linear")
    total_ns = float(np.rint(values * NS_PER_MS).sum())
    return {
        "count": int(values.size), "mean_ms": total_ns / values.size / NS_PER_MS,
        "p50_ms": float(p50), "p95_ms": float(p95), "p99_ms": float(p99), "max_ms": float(values.max()),
    }


Summarizer = Callable[[str, str, np.ndarray], dict]
"""(kind "stages" | "gaps" | "frame", name, values in ms) -> the ``summarize`` dict of them;
the relay's live engine passes one that adds the values of frames already finalised."""


def _plain(kind: str, name: str, values_ms: np.ndarray) -> dict:
    return summarize(values_ms)


def delay_summary(s: Series, summarize_ms: Summarizer = _plain) -> dict:
    """``{"stages", "gaps", "frame", "bottleneck"}``: a ``summarize`` dict per series, each
    stage's with its ``share`` of the mean frame delay."""
    frame = summarize_ms("frame", "frame", s.frame / NS_PER_MS)
    stages = {}
    for name, values in s.stages.items():
        st = summarize_ms("stages", name, values / NS_PER_MS)
        st["share"] = share(st, frame)
        stages[name] = st
    gaps = {name: summarize_ms("gaps", name, values / NS_PER_MS) for name, values in s.gaps.items()}
    return {"stages": stages, "gaps": gaps, "frame": frame, "bottleneck": bottleneck(stages)}


def share(stage: dict, frame: dict) -> float | None:
    """A stage's mean delay over the mean frame delay; None without both."""
    if stage["mean_ms"] is None or not frame["mean_ms"]:
        return None
    return stage["mean_ms"] / frame["mean_ms"]


def bottleneck(stages: dict[str, dict]) -> dict | None:
    """``{stage, mean_ms, share}`` of the stage with the largest mean delay (the first on a tie)."""
    means = {k: v["mean_ms"] for k, v in stages.items() if v["mean_ms"] is not None}
    if not means:
        return None
    name = max(means, key=means.get)
    return {"stage": name, "mean_ms": means[name], "share": stages[name]["share"]}


def fps_by_source(fd: FrameDelays, sources: Iterable[int] = ()) -> dict[str, float]:
    """Source id (str) -> complete frames per second over the span of their origin timestamps.

    With n frames over a span T the rate is (n - 1) / T: n frames mark n - 1 intervals, so a
    10 fps camera reads 10.0, not 10 + 10/n. 0.0 when fewer than two frames completed.
    """
    table, complete = fd.table, fd.chains.complete
    ids = sorted(set(int(s) for s in sources) | set(np.unique(table.source).tolist()))
    out = {}
    for sid in ids:
        origin = table.origin[complete & (table.source == sid)]
        span = int(origin.max() - origin.min()) if origin.size >= 2 else 0
        out[str(sid)] = (origin.size - 1) * 1e9 / span if span > 0 else 0.0
    return out


def node_stats(header: TraceHeader, events: np.ndarray, dropped: int = 0) -> dict:
    """Statistics of one node's events; the shape ``dcuscope stats --json`` prints per node."""
    return delay_stats(frame_delays(frame_table(header, events)), header.sources, dropped)


def delay_stats(fd: FrameDelays, sources: Iterable[int] = (), dropped: int = 0) -> dict:
    """``delay_summary`` of ``fd`` + ``fps`` per source, ``dropped`` events, ``frames``
    (complete and incomplete counts)."""
    n_complete = int(fd.chains.complete.sum())
    return {
        **delay_summary(series(fd)),
        "fps": fps_by_source(fd, sources),
        "dropped": int(dropped),
        "frames": {"complete": n_complete, "incomplete": len(fd) - n_complete},
    }
