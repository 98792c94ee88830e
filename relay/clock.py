"""Clock offset of a node to the relay: NTP-style estimate, and which correction to apply.

The node reads its own PTP state (:mod:`probes.ptp`) and reports it with its clock samples.

Sign convention: ``offset_ns`` is the node's clock minus the relay's clock (a node whose clock
runs 37 ms ahead has offset +37 ms), so a node timestamp is brought to the relay's clock by
subtracting it. From the four NTP timestamps (t1 node send, t2 relay receive, t3 relay send,
t4 node receive) NTP's theta = ((t2 - t1) + (t3 - t4)) / 2 is relay minus node: offset = -theta.
The true offset lies within +-RTT/2 of any sample's estimate (RTT = (t4 - t1) - (t3 - t2)),
whatever the asymmetry of the two paths; the minimum-RTT sample of a window has the tightest
bound, which is the uncertainty reported.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

CLOCK_MODES = ("ptp", "estimate", "auto")
DEFAULT_WINDOW = 32
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


@dataclass(frozen=True)
class ClockEstimate:
    offset_ns: int
    uncertainty_ns: int
    rtt_ns: int
    samples: int


def ntp_sample(t1: int, t2: int, t3: int, t4: int) -> ClockSample:
    """Offset (node - relay) and round-trip delay of one exchange."""
    theta2 = (t2 - t1) + (t3 - t4)
    rtt = (t4 - t1) - (t3 - t2)
    return ClockSample(offset_ns=-theta2 // 2, rtt_ns=max(rtt, 0), at_ns=t2)


class ClockEstimator:
    """Keeps the last ``window`` samples of one node; the estimate is the minimum-RTT one."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        self._samples: deque[ClockSample] = deque(maxlen=window)

    def add(self, t1: int, t2: int, t3: int, t4: int) -> None:
        self.add_sample(ntp_sample(t1, t2, t3, t4))

    def add_sample(self, sample: ClockSample) -> None:
        self._samples.append(sample)

    def estimate(self) -> ClockEstimate | None:
        if not self._samples:
            return None
        best = min(self._samples, key=lambda s: s.rtt_ns)
        return ClockEstimate(best.offset_ns, (best.rtt_ns + 1) // 2, best.rtt_ns, len(self._samples))


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
    auto: trust PTP when the node reports it locked, else subtract the estimate.
    """
    if mode not in CLOCK_MODES:
        raise ValueError(f"clock mode must be one of {CLOCK_MODES}, not {mode!r}")
    if mode == "ptp" or (mode == "auto" and ptp.get("state") == "locked"):
        return 0, "ptp"
    if estimate is None:
        return 0, "none"
    if abs(estimate.offset_ns) > MAX_CORRECTION_NS:  # samples are checked: a bug, never applied
        return 0, "ignored"
    return estimate.offset_ns, "estimate"
