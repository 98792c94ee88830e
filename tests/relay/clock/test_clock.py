"""NTP-style offset estimation and the --clock policy."""

from __future__ import annotations

import numpy as np
import pytest

from dcuscope.relay.clock.correction import ClockEstimate, Correction, Segment, correction_ns, correction_of, ntp_sample
from dcuscope.relay.clock.model import WINDOW_NS, ClockEstimator, half_width


def exchange(offset: int, t1_true: int, up: int, down: int, hold: int) -> tuple[int, int, int, int]:
    """Timestamps of one exchange with a node clock ``offset`` ahead and given path delays."""
    t2 = t1_true + up
    t3 = t2 + hold
    return t1_true + offset, t2, t3, t3 + down + offset


def test_symmetric_exchange_recovers_offset_exactly():
    s = ntp_sample(*exchange(37_000_000, 10**18, 200_000, 200_000, 50_000))
    assert s.offset_ns == 37_000_000 and s.rtt_ns == 400_000


def test_asymmetry_stays_within_half_rtt():
    rng = np.random.default_rng(1)
    for _ in range(1000):
        up, down = rng.integers(10_000, 5_000_000, 2)
        s = ntp_sample(*exchange(-4_000_000, 10**18, int(up), int(down), 10_000))
        assert abs(s.offset_ns - (-4_000_000)) <= (s.rtt_ns + 1) // 2


def test_estimator_keeps_min_delay_sample_of_a_point_and_the_points_of_its_window():
    est = ClockEstimator()
    assert est.estimate() is None
    est.add(*exchange(5_000_000, 10**18, 3_000_000, 100_000, 0))  # asymmetric, large RTT
    est.add(*exchange(5_000_000, 10**18, 60_000, 40_000, 0))     # the best one
    est.add(*exchange(5_000_000, 10**18, 900_000, 100_000, 0))
    e = est.estimate()
    assert e.rtt_ns == 100_000 and e.samples == 3 and e.points == 1
    assert abs(e.offset_ns - 5_000_000) <= e.uncertainty_ns == half_width(100_000) + 1  # +1: rounding
    for k in range(1, 5):  # later points, worse ones: the best stays while it is in the window
        est.add(*exchange(5_000_000, 10**18 + k * 2 * 10**9, 300_000, 300_000, 0))
    assert est.estimate().points == 5 and est.estimate().samples == 7
    est.add(*exchange(5_000_000, 10**18 + WINDOW_NS + 10**9, 300_000, 300_000, 0))
    assert est.estimate().rtt_ns == 600_000 and est.estimate().points == 5  # the first point left the window


def test_correction_policy():
    est = ClockEstimate(offset_ns=37_000, uncertainty_ns=100, rtt_ns=200, samples=3)
    locked = {"state": "locked", "gm_present": True, "port_state": "SLAVE", "master_offset_ns": -80,
              "system_clock": {"synced": True, "by": "phc2sys", "follows_ptp": True}}
    unlocked, none = {"state": "unlocked"}, {"state": "unavailable"}
    assert correction_ns("ptp", est, unlocked) == (0, "ptp")
    assert correction_ns("estimate", est, locked) == (37_000, "estimate")
    assert correction_ns("auto", est, locked) == (0, "ptp")
    assert correction_ns("auto", est, unlocked) == (37_000, "estimate")
    # ptp4l locked but nothing said (an older node) or nothing steering CLOCK_REALTIME: the estimate
    assert correction_ns("auto", est, {"state": "locked"}) == (37_000, "estimate")
    free = dict(locked, system_clock={"synced": False, "by": None, "follows_ptp": False, "detail": "ptp4l free_running"})
    assert correction_ns("auto", est, free) == (37_000, "estimate")
    corr = correction_of("auto", est, free)
    assert corr.applied == "estimate" and corr.why == (
        "PTP not trusted: ptp4l locked but CLOCK_REALTIME not disciplined by PTP (ptp4l free_running); estimate applied")
    trusted = correction_of("auto", est, locked)
    assert trusted.applied == "ptp" and trusted.at(10**18) == (0, 80) and "CLOCK_REALTIME by phc2sys" in trusted.why
    assert correction_ns("auto", None, none) == (0, "none")
    with pytest.raises(ValueError):
        correction_ns("bogus", est, none)


def test_the_correction_at_one_timestamp_is_that_of_the_arrays():
    """``Correction.at`` (a push's head, in Python's arithmetic) equals ``offsets`` and ``uncertainties``
    of the same timestamp (numpy's), before the first segment, at each start, and where a drift's
    product ends in exactly half a nanosecond (both round it to even)."""
    rng = np.random.default_rng(11)
    t0 = 1_700_000_000_000_000_000
    segments = tuple(Segment(t0 + k * 10**9, t0 + k * 10**9 - 5 * 10**8, int(rng.integers(-10**9, 10**9)),
                             drift_ppb=int(rng.integers(-10**5, 10**5)), uncertainty_ns=int(rng.integers(0, 10**6)),
                             growth_ppb=int(rng.integers(0, 10**4))) for k in range(4))
    halves = (Segment(t0, t0, 0, drift_ppb=500, growth_ppb=500), Segment(t0 + 10**9, t0, 7, drift_ppb=1500))
    for corr in (Correction("estimate", "", segments, 250), Correction("estimate", "", halves),
                 Correction("none", "no estimate"), Correction("ptp", "", (), 80)):
        ts = np.concatenate([t0 + rng.integers(-2 * 10**9, 6 * 10**9, 500),
                             [t0 - 1, t0, t0 + 1, t0 + 1_000_000, t0 + 10**9, t0 + 1_001_000_000, t0 + 3 * 10**9 - 1]]).astype(np.int64)
        want = list(zip(corr.offsets(ts).tolist(), corr.uncertainties(ts).tolist()))
        assert [corr.at(int(t)) for t in ts] == want
    # 0.5 ns of drift rounds to 0 (its bound up to 1), 1501.5 ns to 1502: half to even, as numpy's rint
    assert Correction("estimate", "", halves).at(t0 + 1_000_000) == (0, 1)
    assert Correction("estimate", "", halves).at(t0 + 1_001_000_000) == (7 + 1502, 0)
