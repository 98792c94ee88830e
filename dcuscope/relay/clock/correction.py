"""Clock offset of a node to the relay: NTP-style estimate, and which correction to apply.

The node reads its own PTP state (:mod:`dcuscope.probes.clocks.ptp`) and reports it with its clock samples.

Sign convention: ``offset_ns`` is the node's clock minus the relay's clock (a node whose clock
runs 37 ms ahead has offset +37 ms), so a node timestamp is brought to the relay's clock by
subtracting it. From the four NTP timestamps (t1 node send, t2 relay receive, t3 relay send,
t4 node receive) NTP's theta = ((t2 - t1) + (t3 - t4)) / 2 is relay minus node: offset = -theta.
The true offset lies within +-RTT/2 of any sample's estimate (RTT = (t4 - t1) - (t3 - t2)),
whatever the asymmetry of the two paths. :mod:`dcuscope.relay.clock.model` fits offset and drift over
many samples, with a bound that holds at every timestamp, and keeps the history of its estimates.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from dcuscope.model.frametable import MISSING
from dcuscope.protocol.ptptrust import ptp_trusted, ptp_uncertainty_ns

CLOCK_MODES = ("ptp", "estimate", "auto")
UNKNOWN_BOUND = ("none", "ignored", "raw")
"""Corrections whose bound is unknown (no estimate yet): what is compared across nodes cannot be
judged against it."""
MAX_CORRECTION_NS = 10**17
"""The largest correction ever applied (~3 years), whatever ``--limit clock_offset_s`` says: a
timestamp of this era (~1.7e18 ns) moved by it stays far inside int64, so no arithmetic on
corrected timestamps can overflow. A stored one beyond it (an older relay's) is ignored."""


@dataclass(frozen=True)
class ClockSample:
    offset_ns: int
    rtt_ns: int
    at_ns: int
    """Relay time of the sample (t2)."""
    node_ns: int = 0
    """Node time of the sample: (t1 + t4) / 2."""
    via: str = "websocket"
    """Transport of the exchange: websocket (the ingest connection) or udp."""


@dataclass(frozen=True)
class ClockEstimate:
    """A node's offset (node - relay) at node time ``at_ns``, true within ``uncertainty_ns`` there
    and within uncertainty_ns + growth_ppb * |ts - at_ns| / 1e9 at any node time ts, drifting by
    ``drift_ppb`` (:mod:`dcuscope.relay.clock.model`)."""
    offset_ns: int
    uncertainty_ns: int
    rtt_ns: int
    samples: int
    at_ns: int | None = None
    """Node-clock time the estimate holds at (its reference point)."""
    drift_ppb: int = 0
    growth_ppb: int = 0
    """Bound on |drift - true drift|, ppb."""
    via: str = "websocket"
    """Transport of the sample the bound rests on."""
    points: int = 1
    newest_ns: int | None = None
    """Node time of the newest point the estimate rests on."""

    def segment(self, from_ns: int) -> Segment:
        """The estimate in force for node timestamps from ``from_ns`` on."""
        ref = self.at_ns if self.at_ns is not None else from_ns
        return Segment(from_ns=from_ns, ref_ns=ref, offset_ns=self.offset_ns, drift_ppb=self.drift_ppb,
                       uncertainty_ns=self.uncertainty_ns, growth_ppb=self.growth_ppb)


def ntp_sample(t1: int, t2: int, t3: int, t4: int, via: str = "websocket") -> ClockSample:
    """Offset (node - relay) and round-trip delay of one exchange."""
    theta2 = (t2 - t1) + (t3 - t4)
    rtt = (t4 - t1) - (t3 - t2)
    return ClockSample(offset_ns=-theta2 // 2, rtt_ns=max(rtt, 0), at_ns=t2, node_ns=(t1 + t4) // 2, via=via)


def sample_fault(sample: ClockSample, max_offset_ns: int, max_rtt_ns: int) -> str | None:
    """Why a sample cannot be true (its offset or round trip beyond the bounds), or None."""
    if abs(sample.offset_ns) > min(max_offset_ns, MAX_CORRECTION_NS):
        return f"offset {sample.offset_ns} ns beyond {min(max_offset_ns, MAX_CORRECTION_NS)} ns"
    if sample.rtt_ns > max_rtt_ns:
        return f"round trip {sample.rtt_ns} ns beyond {max_rtt_ns} ns"
    return None


def stored_correction(clock: object) -> tuple[int, str | None]:
    """The correction a stored clock view calls for, and why it is ignored (then 0), if it is."""
    value = clock.get("correction_ns", 0) if isinstance(clock, dict) else None
    if value is None:
        return 0, None if isinstance(clock, dict) else "not a clock record"
    if not isinstance(value, int) or isinstance(value, bool):
        return 0, f"correction {str(value)[:40]!r} is not an integer"
    if abs(value) > MAX_CORRECTION_NS:
        return 0, f"correction {value} ns beyond {MAX_CORRECTION_NS} ns"
    return value, None


def correction_ns(mode: str, estimate: ClockEstimate | None, ptp: dict) -> tuple[int, str]:
    """What to subtract from the node's timestamps under ``--clock mode``, and why.

    ptp: never correct (PTP is trusted); estimate: always subtract the estimated offset;
    auto: trust PTP where :func:`dcuscope.protocol.ptptrust.ptp_trusted` does (a locked slave port *and*
    CLOCK_REALTIME following it), else subtract the estimate.
    """
    if mode not in CLOCK_MODES:
        raise ValueError(f"clock mode must be one of {CLOCK_MODES}, not {mode!r}")
    if mode == "ptp" or (mode == "auto" and ptp_trusted(ptp)[0]):
        return 0, "ptp"
    if estimate is None:
        return 0, "none"
    if abs(estimate.offset_ns) > MAX_CORRECTION_NS:  # samples are checked: a bug, never applied
        return 0, "ignored"
    return estimate.offset_ns, "estimate"


@dataclass(frozen=True)
class Segment:
    """One estimate of a node's clock, in force for node timestamps from ``from_ns`` on (the
    first segment of a history also before): offset(ts) = offset_ns + drift_ppb * (ts - ref_ns) / 1e9,
    true within uncertainty_ns + growth_ppb * |ts - ref_ns| / 1e9."""
    from_ns: int
    ref_ns: int
    offset_ns: int
    drift_ppb: int = 0
    uncertainty_ns: int = 0
    growth_ppb: int = 0

    def to_dict(self) -> dict:
        return {"from_ns": self.from_ns, "ref_ns": self.ref_ns, "offset_ns": self.offset_ns,
                "drift_ppb": self.drift_ppb, "uncertainty_ns": self.uncertainty_ns, "growth_ppb": self.growth_ppb}


@dataclass(frozen=True)
class Correction:
    """What is subtracted from one run's node timestamps to bring them to the relay's clock, per
    timestamp (a history of estimates, each with its drift), and how far it may be off.

    ``applied``: ptp (PTP trusted, nothing subtracted), estimate, none (no estimate yet),
    ignored (a stored correction no relay could compute), raw (asked for uncorrected times).
    No segments: nothing subtracted, uncertainty ``base_uncertainty_ns`` (unknown: 0 with applied none).
    """
    applied: str
    why: str = ""
    segments: tuple[Segment, ...] = ()
    base_uncertainty_ns: int = 0

    @cached_property
    def _table(self) -> dict[str, np.ndarray]:
        """The segments' fields as arrays (looked up by index), built once."""
        seg = self.segments
        return {"from": np.array([s.from_ns for s in seg], np.int64), "offset": np.array([s.offset_ns for s in seg], np.int64),
                "drift": np.array([s.drift_ppb for s in seg], np.float64), "ref": np.array([s.ref_ns for s in seg], np.int64),
                "unc": np.array([s.uncertainty_ns for s in seg], np.int64),
                "growth": np.array([s.growth_ppb for s in seg], np.float64)}

    @cached_property
    def segment_addresses(self) -> tuple[int, ...]:
        """Where the segments' fields lie as arrays (``from``, ``ref``, ``offset``, ``drift``, ``unc``,
        ``growth``; drift and growth float64, the others int64), as the compiled push reads them (taken once)."""
        return tuple(self._table[name].ctypes.data for name in ("from", "ref", "offset", "drift", "unc", "growth"))

    def _index(self, ts: np.ndarray) -> np.ndarray:
        return np.maximum(np.searchsorted(self._table["from"], ts, side="right") - 1, 0)

    def offsets(self, ts: np.ndarray, at: np.ndarray | None = None) -> np.ndarray:
        """(n,) int64 ns to subtract from each node timestamp of ``ts``, by the segment in force at
        ``ts`` or, given ``at`` (same shape), at ``at`` (a frame's start: one estimate per frame)."""
        ts = np.asarray(ts, dtype=np.int64)
        if not self.segments:
            return np.zeros(ts.shape, dtype=np.int64)
        return self.per_frame(ts if at is None else at).offsets(ts)

    def uncertainties(self, ts: np.ndarray, at: np.ndarray | None = None) -> np.ndarray:
        """(n,) int64 ns: bound on |true offset - applied offset| at each timestamp (``at`` as in :meth:`offsets`)."""
        ts = np.asarray(ts, dtype=np.int64)
        if not self.segments:
            return np.full(ts.shape, self.base_uncertainty_ns, dtype=np.int64)
        return self.per_frame(ts if at is None else at).uncertainties(ts)

    def per_frame(self, at: np.ndarray) -> FrameCorrection:
        """The segment in force at each of ``at`` (a frame's origin), looked up once for every
        timestamp of the frame (:class:`FrameCorrection`)."""
        at = np.asarray(at, dtype=np.int64)
        if not self.segments:
            zero = np.zeros(at.shape, np.int64)
            return FrameCorrection(zero, zero, zero.astype(np.float64), zero + self.base_uncertainty_ns, zero.astype(np.float64))
        seg, t = self._index(at), self._table
        return FrameCorrection(t["offset"][seg], t["ref"][seg], t["drift"][seg], t["unc"][seg] + self.base_uncertainty_ns,
                               t["growth"][seg])

    def at(self, ts: int) -> tuple[int, int]:
        """(offset, uncertainty) in ns at one node timestamp: :meth:`offsets` and :meth:`uncertainties`
        of it, in Python's arithmetic (the same float64 operations and rounding; a push asks once a
        run, where numpy's would cost more than the frames' own)."""
        if not self.segments:
            return 0, self.base_uncertainty_ns
        s = self.segments[max(bisect_right(self._froms, ts) - 1, 0)]
        off = s.offset_ns + int(round(float(s.drift_ppb) * float(ts - s.ref_ns) / 1e9))
        unc = s.uncertainty_ns + self.base_uncertainty_ns + math.ceil(float(s.growth_ppb) * float(abs(ts - s.ref_ns)) / 1e9)
        return off, unc

    @cached_property
    def _froms(self) -> tuple[int, ...]:
        return tuple(s.from_ns for s in self.segments)

    def correct(self, ts: np.ndarray, at: np.ndarray | None = None) -> np.ndarray:
        """Node timestamps moved to the relay's clock (MISSING kept as it is); ``at`` as in :meth:`offsets`."""
        ts = np.asarray(ts, dtype=np.int64)
        return np.where(ts == MISSING, ts, ts - self.offsets(ts, at))

    def on_relay_clock(self) -> Correction:
        """The same correction looked up by corrected times (for timestamps already moved): each
        segment starts where its own start lands on the relay's clock, its drift per relay ns. Off
        by the drift's rounding (1 ns per s from the reference), and ambiguous within a jump of the
        offset from one segment to the next (microseconds; a step's size) of a segment's start."""
        moved = tuple(replace(s, from_ns=s.from_ns - self.at(s.from_ns)[0], ref_ns=s.ref_ns - s.offset_ns,
                              drift_ppb=round(s.drift_ppb / (1 - s.drift_ppb / 1e9))) for s in self.segments)
        return replace(self, segments=moved)

    def to_dict(self) -> dict:
        return {"applied": self.applied, "why": self.why, "base_uncertainty_ns": self.base_uncertainty_ns,
                "segments": [s.to_dict() for s in self.segments]}


@dataclass(frozen=True)
class FrameCorrection:
    """One segment of a :class:`Correction` per frame: offsets and bounds of timestamps of shape
    (n,), one per frame, or (n, k), a frame's k timestamps per row."""
    offset: np.ndarray
    ref: np.ndarray
    drift: np.ndarray
    uncertainty: np.ndarray
    """The segment's bound plus the correction's base bound."""
    growth: np.ndarray

    def offsets(self, ts: np.ndarray, columns: bool = False) -> np.ndarray:
        """``columns``: ``ts`` is (k, n), a frame's k timestamps per column (no transposes needed)."""
        ts = np.asarray(ts, dtype=np.int64)
        off, ref, drift = ((a if columns else _rows(a, ts)) for a in (self.offset, self.ref, self.drift))
        return off + np.rint(drift * (ts - ref).astype(np.float64) / 1e9).astype(np.int64)

    def uncertainties(self, ts: np.ndarray) -> np.ndarray:
        ts = np.asarray(ts, dtype=np.int64)
        unc, ref, growth = (_rows(a, ts) for a in (self.uncertainty, self.ref, self.growth))
        return unc + np.ceil(growth * np.abs(ts - ref).astype(np.float64) / 1e9).astype(np.int64)

    def correct(self, ts: np.ndarray, columns: bool = False) -> np.ndarray:
        """Node timestamps moved to the relay's clock (MISSING kept as it is); ``columns`` as in :meth:`offsets`."""
        ts = np.asarray(ts, dtype=np.int64)
        return np.where(ts == MISSING, ts, ts - self.offsets(ts, columns))


def _rows(per_frame: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """``per_frame`` shaped to broadcast over ``ts``'s rows."""
    return per_frame.reshape(per_frame.shape + (1,) * (ts.ndim - per_frame.ndim)) if ts.ndim > per_frame.ndim else per_frame


NO_CORRECTION = Correction("none", "no clock estimate yet")


def correction_of(mode: str, estimate: ClockEstimate | None, ptp: dict, now_ns: int | None = None,
                  history: tuple[Segment, ...] | list[Segment] = ()) -> Correction:
    """The :class:`Correction` ``--clock mode`` calls for (see :func:`correction_ns`): under an
    estimate, the ``history`` of estimates (each in force from its ``from_ns``), else the estimate alone."""
    value, applied = correction_ns(mode, estimate, ptp)
    reason = ptp_trusted(ptp)[1] if mode == "auto" else ""
    if applied == "ptp":
        unc = ptp_uncertainty_ns(ptp) if isinstance(ptp, dict) else 0
        return Correction("ptp", reason if mode == "auto" else "--clock ptp", (), unc)
    untrusted = f"PTP not trusted: {reason}; " if mode == "auto" else ""
    if applied == "none" and history:  # a run resumed after a relay restart: its stored estimates hold
        applied = "estimate"
    elif applied != "estimate" or estimate is None:
        return Correction(applied, untrusted + ("no clock estimate yet" if applied == "none" else "estimate ignored"))
    why = untrusted + "estimate applied" if mode == "auto" else "offset estimated by the relay"
    if history:
        return Correction("estimate", why, tuple(history))
    at = estimate.at_ns if estimate.at_ns is not None else (now_ns or 0)
    return Correction("estimate", why, (estimate.segment(at),))
