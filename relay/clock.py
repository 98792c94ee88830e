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
        self._samples.append(ntp_sample(t1, t2, t3, t4))

    def estimate(self) -> ClockEstimate | None:
        if not self._samples:
            return None
        best = min(self._samples, key=lambda s: s.rtt_ns)
        return ClockEstimate(best.offset_ns, (best.rtt_ns + 1) // 2, best.rtt_ns, len(self._samples))


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
    return estimate.offset_ns, "estimate"
