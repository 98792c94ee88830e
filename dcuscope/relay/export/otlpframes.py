"""The figures of the frames chosen for OpenTelemetry export, copied out of a finalised batch.

Only the numbers a trace needs, clock-corrected exactly as :mod:`dcuscope.relay.live.framejson` corrects
frames for the UI (every timestamp of a frame by the estimate in force at its origin), so that
a span's times are the ones ``/api/frames`` shows and its length the delay the relay derived.
Copies, not views: the exporter's thread reads them while the event loop goes on.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from dcuscope.model.delays import FrameDelays
from dcuscope.model.frametable import MISSING
from dcuscope.relay.clock.correction import Correction


@dataclass(frozen=True)
class FrameBatch:
    """``k`` frames of one run; per-frame arrays (k,) and per-stage ones (k, stages). Timestamps
    int64 ns on the relay's clock, MISSING where a frame has none; delays float64 ns, NaN where
    the delay model has none."""
    node: str
    run: str
    stages: tuple[str, ...]
    kinds: dict[str, str]
    uris: dict[int, str]
    clock: str
    """The correction applied: ptp, estimate, none (relay.clock.correction.Correction.applied)."""
    limit_ns: int | None
    source: np.ndarray
    frame: np.ndarray
    over: np.ndarray
    """Over the node's frame limit (else chosen by the 1-in-N sample)."""
    origin: np.ndarray
    end: np.ndarray
    capture: np.ndarray
    """The camera's clock: never corrected (as /api/frames)."""
    delay: np.ndarray
    glass: np.ndarray
    clock_ns: np.ndarray
    """Offset subtracted from the frame's timestamps (the node's clock minus the relay's)."""
    uncertainty_ns: np.ndarray
    enter: np.ndarray
    exit: np.ndarray
    start: np.ndarray
    """When the stage began the work that carried the frame out (enter + wait), MISSING without a ready time."""
    before: np.ndarray
    """The previous stage's exit (or the origin) a gap starts at, MISSING where the frame has no gap there."""
    prev: np.ndarray
    """Index of the stage the gap comes from, -1 for none."""
    stage_delay: np.ndarray
    gap: np.ndarray
    service: np.ndarray
    wait: np.ndarray

    def __len__(self) -> int:
        return int(self.source.shape[0])

    def split(self, n: int) -> tuple[FrameBatch, FrameBatch]:
        """The first ``n`` frames and the rest."""
        arrays = [f.name for f in fields(self) if isinstance(getattr(self, f.name), np.ndarray)]
        return (replace(self, **{a: getattr(self, a)[:n] for a in arrays}),
                replace(self, **{a: getattr(self, a)[n:] for a in arrays}))


def copy_frames(node: str, run: str, kinds: dict[str, str], uris: dict[int, str], fd: FrameDelays,
                rows: np.ndarray, over: np.ndarray, corr: Correction, limit_ns: int | None) -> FrameBatch:
    """The frames ``rows`` of ``fd`` (complete ones), ``over`` their limit or not, corrected by ``corr``."""
    t, ch, per = fd.table, fd.chains, fd.per_stage
    origin = t.origin[rows]
    at = np.broadcast_to(origin[:, None], (len(rows), len(t.stages)))
    enter, exit_ = t.enter[rows], t.exit[rows]
    service = per["service"][rows]
    # framejson's start: ready clamped into [enter, exit]; wait = start - enter, service = exit - start.
    start = np.where(np.isnan(service), MISSING, np.minimum(np.maximum(t.ready[rows], enter), exit_))
    prev = ch.prev[rows]
    gap = per["gap"][rows]
    before = ch.t_out[rows[:, None], np.maximum(prev, 0)]
    before = np.where(np.isnan(gap), MISSING, before)
    end = ch.end[rows]
    glass = fd.glass[rows] - corr.offsets(end, origin).astype(np.float64)
    return FrameBatch(
        node=node, run=run, stages=tuple(t.stages), kinds=dict(kinds), uris=dict(uris), clock=corr.applied,
        limit_ns=limit_ns, source=t.source[rows].copy(), frame=t.frame[rows].copy(), over=np.array(over, bool),
        origin=corr.correct(origin), end=corr.correct(end, origin), capture=t.capture[rows].copy(),
        delay=fd.delay[rows].copy(), glass=glass, clock_ns=corr.offsets(origin),
        uncertainty_ns=corr.uncertainties(origin),
        enter=corr.correct(enter, at), exit=corr.correct(exit_, at), start=corr.correct(start, at),
        before=corr.correct(before, at), prev=prev.copy(), stage_delay=per["delay"][rows].copy(), gap=gap.copy(),
        service=service.copy(), wait=per["wait"][rows].copy())
