"""The relay's model of one node's clock: offset and drift from NTP samples, a rigorous bound,
and the history of its estimates (what corrects each node timestamp).

Points. Samples (t1..t4, any transport) whose node times fall in one ``POINT_SPAN_NS`` slot of
the node's clock form a point, which keeps their minimum-RTT sample. Whatever the paths'
asymmetry, the true offset at a point's node time lies within its offset +- r, r = RTT/2 + the
drift over half the exchange (at most ``MAX_DRIFT_PPB``) + ``TIMESTAMP_FLOOR_NS`` (reading and rounding).

Fit. Over the points of the last ``WINDOW_NS`` (at most ``MAX_POINTS``): offset = a + b (t - ref),
least squares weighted by 1/r^2, b the drift (clamped to +-``MAX_DRIFT_PPB``). Over a span under
``MIN_DRIFT_SPAN_NS`` or fewer than ``MIN_DRIFT_POINTS`` points: b = 0, a = the min-RTT point's offset.

Bound. If the clock's offset is linear in time over the window (constant drift), the error
e(t) = truth - fit is linear too, and at every point |e(t_i)| <= E_i = |residual_i| + r_i. With p the
point of least E among the earliest quarter of the window's span and q the same among the latest:
|e(t)| <= E_q + G |t - t_q| for every t, where G = (E_p + E_q) / (t_q - t_p) bounds |b - b_true|.
With a single point no slope is seen: G = MAX_DRIFT_PPB + |b|, a clock drifting faster than
``MAX_DRIFT_PPB`` being taken as broken (the kernel disciplines a clock within 500 ppm).

Steps. A sample outside the current bound (its interval disjoint from the fit's) proves the
clock was not linear over the window (stepped, or changed its frequency): the window restarts
at that sample.

History. Each new estimate becomes a :class:`Segment` in force from the node time of the newest
point before its report (the times since then it interpolates, those after it extrapolates; after
a restart: from its first point); one made within ``HISTORY_MIN_NS`` (relay time) of the last
appended replaces that one. At most ``MAX_HISTORY`` are kept: beyond, the segment its
predecessor predicts best goes.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field, replace

import numpy as np

from dcuscope.relay.clock.correction import MAX_CORRECTION_NS, ClockEstimate, ClockSample, Segment, ntp_sample

POINT_SPAN_NS = 1_000_000_000
WINDOW_NS = 600_000_000_000
MAX_POINTS = 600
MIN_DRIFT_SPAN_NS = 20_000_000_000
MIN_DRIFT_POINTS = 5
MAX_DRIFT_PPB = 500_000
TIMESTAMP_FLOOR_NS = 1_000
HISTORY_MIN_NS = 1_500_000_000
MAX_HISTORY = 256


def half_width(rtt_ns: int) -> int:
    """r of a sample: RTT/2, what the clock may drift while half the exchange lasts, the floor."""
    return (rtt_ns + 1) // 2 + rtt_ns * MAX_DRIFT_PPB // 2_000_000_000 + 1 + TIMESTAMP_FLOOR_NS


@dataclass
class Point:
    """The minimum-RTT sample of the samples taken in the POINT_SPAN_NS slot from ``start_ns`` (node time)."""
    start_ns: int
    node_ns: int
    offset_ns: int
    rtt_ns: int
    relay_ns: int
    via: str
    samples: int = 1

    @property
    def half_ns(self) -> int:
        """r: the true offset at ``node_ns`` lies within offset_ns +- r."""
        return half_width(self.rtt_ns)

    def take(self, s: ClockSample) -> None:
        self.samples += 1
        if s.rtt_ns < self.rtt_ns:
            self.node_ns, self.offset_ns, self.rtt_ns, self.relay_ns, self.via = (
                s.node_ns, s.offset_ns, s.rtt_ns, s.at_ns, s.via)


def point_of(s: ClockSample) -> Point:
    return Point(s.node_ns - s.node_ns % POINT_SPAN_NS, s.node_ns, s.offset_ns, s.rtt_ns, s.at_ns, s.via)


def fit(points: list[Point]) -> ClockEstimate:
    """The estimate over ``points`` (node time order, at least one) and its bound (module doc)."""
    t = np.array([p.node_ns for p in points], dtype=np.int64)
    o = np.array([p.offset_ns for p in points], dtype=np.int64)
    r = np.array([p.half_ns for p in points], dtype=np.float64)
    best = int(np.argmin(r))
    # Differences from the best point keep float64 exact to well under a nanosecond.
    dt, do = (t - t[best]).astype(np.float64), (o - o[best]).astype(np.float64)
    span = int(t[-1] - t[0])
    drift = 0.0
    if span >= MIN_DRIFT_SPAN_NS and len(points) >= MIN_DRIFT_POINTS:
        w = 1.0 / (r * r)
        tm, om = np.average(dt, weights=w), np.average(do, weights=w)
        drift = float(np.sum(w * (dt - tm) * (do - om)) / np.sum(w * (dt - tm) ** 2))
        drift = min(max(drift, -MAX_DRIFT_PPB / 1e9), MAX_DRIFT_PPB / 1e9)
        level = om - drift * tm
    else:
        level = 0.0
    e = np.abs(do - (level + drift * dt)) + r
    early = np.flatnonzero(t <= t[0] + span // 4)
    late = np.flatnonzero(t >= t[-1] - span // 4)
    p, q = int(early[np.argmin(e[early])]), int(late[np.argmin(e[late])])
    prior = MAX_DRIFT_PPB / 1e9 + abs(drift)
    growth = min((e[p] + e[q]) / float(t[q] - t[p]), prior) if t[q] > t[p] else prior
    offset_q = int(o[best]) + round(level + drift * dt[q])
    # +1: the offset and drift are rounded to whole ns and ppb.
    return ClockEstimate(offset_ns=offset_q, uncertainty_ns=math.ceil(e[q]) + 1, rtt_ns=points[q].rtt_ns,
                         samples=sum(pt.samples for pt in points), at_ns=int(t[q]), drift_ppb=round(drift * 1e9),
                         growth_ppb=math.ceil(growth * 1e9) + 1, via=points[q].via, points=len(points),
                         newest_ns=int(t[-1]))


def _outside(est: ClockEstimate, s: ClockSample) -> bool:
    """Whether sample ``s`` cannot be true if ``est``'s bound is: their intervals are disjoint."""
    seg = est.segment(est.at_ns)
    dt = s.node_ns - seg.ref_ns
    predicted = seg.offset_ns + seg.drift_ppb * dt / 1e9
    bound = seg.uncertainty_ns + seg.growth_ppb * abs(dt) / 1e9
    return abs(s.offset_ns - predicted) > bound + half_width(s.rtt_ns)


@dataclass
class ClockEstimator:
    """One run's clock model: points in a window, the current estimate, the history of estimates."""
    points: list[Point] = field(default_factory=list)
    history: list[Segment] = field(default_factory=list)
    """Estimates in force from their ``from_ns`` (node time), oldest first."""
    restarts: int = 0
    """Windows restarted because a sample fell outside the bound (a step)."""
    _estimate: ClockEstimate | None = field(default=None, init=False, repr=False)
    _appended_ns: int | None = field(default=None, init=False, repr=False)
    """Relay time of the newest sample when the last history segment was appended."""
    _restarted: bool = field(default=False, init=False, repr=False)
    version: int = field(default=0, init=False)
    """Counts the reports taken: the estimate and the history change with a report, and only then."""

    def add(self, t1: int, t2: int, t3: int, t4: int, via: str = "websocket") -> None:
        self.add_samples([ntp_sample(t1, t2, t3, t4, via)])

    def add_sample(self, sample: ClockSample) -> None:
        self.add_samples([sample])

    def add_samples(self, samples: list[ClockSample]) -> None:
        """Take the samples of one report, then estimate again and note the estimate in the history."""
        if not samples:
            return
        before = self.points[-1].node_ns if self.points else None
        for s in samples:
            self._take(s)
        newest = max(p.node_ns for p in self.points)
        self.points = [p for p in self.points if p.node_ns >= newest - WINDOW_NS][-MAX_POINTS:]
        self._estimate = fit(self.points)
        self._note(self.points[0].node_ns if before is None or self._restarted else before,
                   max(s.at_ns for s in samples))
        self.version += 1

    def _take(self, s: ClockSample) -> None:
        if self._estimate is not None and _outside(self._estimate, s):
            # Only what was measured after it (relay time: node times a step back made ambiguous) stays.
            self.points = [p for p in self.points if p.relay_ns > s.at_ns]
            self._estimate, self._restarted = None, True
            self.restarts += 1
        new = point_of(s)
        for p in reversed(self.points):  # sorted by slot: samples mostly join the newest
            if p.start_ns == new.start_ns:
                p.take(s)
                return
            if p.start_ns < new.start_ns:
                break
        bisect.insort(self.points, new, key=lambda p: p.start_ns)

    def estimate(self) -> ClockEstimate | None:
        return self._estimate

    def _note(self, from_ns: int, relay_ns: int) -> None:
        seg = self._estimate.segment(from_ns)
        last = self.history[-1] if self.history else None
        recent = self._appended_ns is not None and relay_ns - self._appended_ns < HISTORY_MIN_NS
        if last is not None and recent and not self._restarted:
            self.history[-1] = replace(seg, from_ns=last.from_ns)
            return
        # A clock stepped back re-uses node times: the newest estimate holds for them.
        while self.history and self.history[-1].from_ns >= seg.from_ns:
            self.history.pop()
        self.history.append(seg)
        self._appended_ns, self._restarted = relay_ns, False
        if len(self.history) > MAX_HISTORY:
            del self.history[_most_redundant(self.history)]


def _most_redundant(history: list[Segment]) -> int:
    """Index of the segment (not the first or the last) its predecessor predicts best at its start."""
    def miss(i: int) -> float:
        prev, seg = history[i - 1], history[i]
        predicted = prev.offset_ns + prev.drift_ppb * (seg.from_ns - prev.ref_ns) / 1e9
        return abs(predicted - seg.offset_ns - seg.drift_ppb * (seg.from_ns - seg.ref_ns) / 1e9)
    return min(range(1, len(history) - 1), key=miss)


MAX_STORED_DRIFT_PPB = 2 * MAX_DRIFT_PPB


def segment_fault(seg: Segment) -> str | None:
    """Why a stored segment cannot come from this relay (values out of the ranges it computes), or None."""
    limits = (("offset", seg.offset_ns, MAX_CORRECTION_NS), ("drift", seg.drift_ppb, MAX_STORED_DRIFT_PPB),
              ("uncertainty", seg.uncertainty_ns, MAX_CORRECTION_NS), ("growth", seg.growth_ppb, MAX_STORED_DRIFT_PPB),
              ("time", seg.from_ns, 1 << 62), ("reference time", seg.ref_ns, 1 << 62))
    for name, value, bound in limits:
        if not isinstance(value, int) or isinstance(value, bool) or abs(value) > bound:
            return f"{name} {str(value)[:40]} beyond {bound}"
    if seg.uncertainty_ns < 0 or seg.growth_ppb < 0:
        return "negative bound"
    return None
