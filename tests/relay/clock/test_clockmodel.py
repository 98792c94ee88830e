"""The clock model on synthetic exchanges with a known truth: offsets of seconds, drifts up to
+-100 ppm, jitter, asymmetric paths, steps. The truth lies inside the stated bound at every tested
node timestamp, the one the live relay had at each report (extrapolated up to the next) and the
history's afterwards (each timestamp by the estimate in force at its time); the drift is recovered."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from dcuscope.relay.clock.correction import Correction, ClockEstimate, Segment, correction_of, ntp_sample
from dcuscope.relay.clock.model import (HISTORY_MIN_NS, MAX_HISTORY, TIMESTAMP_FLOOR_NS, ClockEstimator, half_width,
                              segment_fault)

T0 = 1_790_000_000_000_000_000
S = 1_000_000_000


@dataclass
class Clock:
    """A node clock: offset (node - true) = offset + drift * tau (+ step from step_at), tau = true time - T0."""
    offset_ns: int
    drift_ppm: float = 0.0
    step_ns: int = 0
    step_at_ns: int = 1 << 62

    def theta(self, tau: float) -> float:
        return self.offset_ns + self.drift_ppm * 1e-6 * tau + (self.step_ns if tau >= self.step_at_ns else 0)

    def node(self, tau: float) -> int:
        """Node clock reading (ns, absolute) at true time T0 + tau."""
        return T0 + round(tau + self.theta(tau))

    def truth_at_node(self, node_ns: np.ndarray, stepped: bool | None = None) -> np.ndarray:
        """True offset at each node timestamp (the clock read it), float ns; ``stepped`` picks
        the side of the step (a step back makes node times ambiguous), by default the one they fit."""
        n = (np.asarray(node_ns) - T0).astype(np.float64)
        b = self.drift_ppm * 1e-6
        before = (n - self.offset_ns) / (1 + b)
        after = (n - self.offset_ns - self.step_ns) / (1 + b)
        tau = np.where(after >= self.step_at_ns, after, before) if stepped is None else (after if stepped else before)
        return np.array([self.theta(v) for v in tau])


def exchange(clock: Clock, tau: float, up: float, down: float, hold: float = 5_000) -> list[int]:
    t2 = T0 + round(tau + up)
    t3 = t2 + round(hold)
    return [clock.node(tau), t2, t3, clock.node(tau + up + hold + down)]


def delays(rng, kind: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(up, down) path delays, ns: loopback websocket, loopback UDP, netem 2 ms +- jitter, 1 ms / 3 ms, seconds."""
    if kind == "websocket":
        return rng.uniform(60_000, 150_000, n) + rng.exponential(20_000, n), rng.uniform(60_000, 150_000, n)
    if kind == "udp":
        return rng.uniform(5_000, 15_000, n), rng.uniform(5_000, 15_000, n) + rng.exponential(3_000, n)
    if kind == "netem":
        return 2e6 + rng.normal(0, 200_000, n).clip(-1.9e6), 2e6 + rng.normal(0, 200_000, n).clip(-1.9e6)
    if kind == "asymmetric":
        return 1e6 + rng.exponential(50_000, n), 3e6 + rng.exponential(50_000, n)
    if kind == "slow":  # a congested link: exchanges of seconds, over which the clock drifts too
        return rng.uniform(0.3e9, 0.5e9, n), rng.uniform(1.0e9, 1.5e9, n)
    raise ValueError(kind)


def run(clock: Clock, kind: str, seconds: int, every_s: float = 2.0, burst: int = 4, seed: int = 0,
        check_ahead_s: float = 3.0) -> tuple[ClockEstimator, list[int]]:
    """Reports of ``burst`` exchanges every ``every_s`` for ``seconds``; after each, the live
    correction holds the truth from its newest point to ``check_ahead_s`` beyond."""
    rng = np.random.default_rng(seed)
    est = ClockEstimator()
    node_times = []
    for k in range(int(seconds / every_s)):
        tau = k * every_s * S + rng.uniform(0, 0.1 * S)
        up, down = delays(rng, kind, burst)
        samples = [exchange(clock, tau + i * 1e6, up[i], down[i]) for i in range(burst)]
        for s in samples:
            est.add(*s)
        node_times += [s[0] for s in samples]
        live = correction_of("estimate", est.estimate(), {}, history=est.history)
        newest = est.estimate().newest_ns
        ahead = np.linspace(newest, newest + check_ahead_s * S, 7).astype(np.int64)
        # Nothing can foresee a step: not checked across one not yet seen.
        stepped = tau >= clock.step_at_ns
        _holds(clock, live, ahead if stepped else ahead[ahead < clock.node(clock.step_at_ns - 1)], stepped)
    return est, node_times


def _holds(clock: Clock, corr: Correction, ts: np.ndarray, stepped: bool | None = None) -> float:
    """The truth within the bound at every ``ts``; returns the largest error."""
    err = np.abs(clock.truth_at_node(ts, stepped) - corr.offsets(ts))
    bound = corr.uncertainties(ts)
    worst = int(np.argmax(err - bound))
    assert (err <= bound).all(), f"at node time {ts[worst]}: error {err[worst]:.0f} ns > bound {bound[worst]} ns"
    return float(err.max())


def history_holds(clock: Clock, est: ClockEstimator, node_times: list[int], ahead_s: float = 60) -> float:
    corr = Correction("estimate", "", tuple(est.history))
    ts = np.linspace(node_times[0], node_times[-1] + ahead_s * S, 2000).astype(np.int64)
    return _holds(clock, corr, ts)


@pytest.mark.parametrize("kind, offset, drift_ppm", [
    ("websocket", 3_700_000, 0.0), ("websocket", -2_500_000_000, 100.0), ("udp", 1_200_000_000, -100.0),
    ("netem", 40_000_000, 50.0), ("asymmetric", -7_000_000, -30.0), ("asymmetric", 2_000_000_000, 100.0),
    ("slow", 300_000_000, -100.0)])
def test_truth_inside_the_bound_live_and_by_history(kind, offset, drift_ppm):
    clock = Clock(offset, drift_ppm)
    est, times = run(clock, kind, 120)
    history_holds(clock, est, times)
    e = est.estimate()
    assert abs(e.drift_ppb - drift_ppm * 1e3) <= e.growth_ppb  # the drift is recovered within its bound
    if kind == "asymmetric":  # 1 ms / 3 ms: the error is 1 ms, the bound RTT/2 = 2 ms
        error = abs(e.offset_ns - clock.truth_at_node(np.array([e.at_ns]))[0])
        assert 950_000 <= error <= 1_050_000 and 2_000_000 <= e.uncertainty_ns <= 2_100_000


@pytest.mark.parametrize("kind, goal_ns", [("websocket", 200_000), ("udp", 30_000)])
def test_ten_minutes_at_50_ppm_recover_the_drift_and_stay_within_the_bound(kind, goal_ns):
    clock = Clock(-900_000_000, 50.0)
    est, times = run(clock, kind, 900, burst=8 if kind == "udp" else 4, seed=3, check_ahead_s=10)
    history_holds(clock, est, times, ahead_s=600)
    e = est.estimate()
    assert abs(e.drift_ppb - 50_000) <= e.growth_ppb
    assert e.growth_ppb <= (1_000 if kind == "websocket" else 100)  # drift known to 1 / 0.1 ppm
    assert e.uncertainty_ns <= goal_ns
    assert abs(e.offset_ns - clock.truth_at_node(np.array([e.at_ns]))[0]) <= e.uncertainty_ns
    assert e.points <= 600 and len(est.history) <= MAX_HISTORY


def test_udp_samples_tighten_a_websocket_estimate_and_name_their_transport():
    clock = Clock(5_000_000, 20.0)
    rng = np.random.default_rng(5)
    est = ClockEstimator()
    for k in range(40):
        tau = k * 2 * S
        for via, kind in (("websocket", "websocket"), ("udp", "udp")):
            up, down = delays(rng, kind, 4)
            for i in range(4):
                est.add(*exchange(clock, tau + i * 1e6 + (5e8 if via == "udp" else 0), up[i], down[i]), via=via)
        if k == 0:
            assert est.estimate().via == "udp"
    e = est.estimate()
    assert e.via == "udp" and e.uncertainty_ns <= 20_000 + TIMESTAMP_FLOOR_NS
    history_holds(clock, est, [clock.node(0), clock.node(80 * S)])


@pytest.mark.parametrize("step_ns", [5_000_000, -3_000_000_000, 400_000])
def test_a_step_restarts_the_window_and_each_part_is_corrected_by_its_own_estimate(step_ns):
    step_at = 61 * S
    clock = Clock(20_000_000, 30.0, step_ns, step_at)
    est, times = run(clock, "websocket", 120, check_ahead_s=1.5)
    assert est.restarts == 1
    corr = Correction("estimate", "", tuple(est.history))
    # Node times a step back made ambiguous hold for the clock after it (the newest estimate).
    before = np.linspace(times[0], min(clock.node(step_at - 1), clock.node(step_at - 1) + step_ns), 500)
    # Between the step and the first report after it, nothing can know: from that report on.
    first_after = clock.node(step_at + 2.1 * S)
    after = np.linspace(first_after, times[-1] + 30 * S, 500)
    _holds(clock, corr, before.astype(np.int64), stepped=False)
    _holds(clock, corr, after.astype(np.int64), stepped=True)


def test_one_point_grows_at_the_largest_drift_and_two_bound_the_slope():
    clock = Clock(1_000_000, 100.0)
    est = ClockEstimator()
    est.add(*exchange(clock, 0, 100_000, 100_000))
    e = est.estimate()
    assert e.drift_ppb == 0 and e.growth_ppb == 500_001  # no slope seen: the prior (+1 for rounding)
    _holds(clock, correction_of("estimate", e, {}), clock.node(0) + np.arange(0, 20 * S, S, dtype=np.int64))
    est.add(*exchange(clock, 2 * S, 100_000, 100_000))
    e = est.estimate()
    assert e.drift_ppb == 0 and 100_000 < e.growth_ppb < 500_000  # (E_p + E_q) / 2 s: span too short to fit
    _holds(clock, correction_of("estimate", e, {}), clock.node(2 * S) + np.arange(0, 20 * S, S, dtype=np.int64))


def test_history_is_thinned_keeping_steps_and_throttled_by_relay_time():
    est = ClockEstimator()
    clock = Clock(0, 10.0)
    for k in range(MAX_HISTORY + 100):
        est.add(*exchange(clock, k * 2 * S, 50_000, 50_000))
    assert len(est.history) == MAX_HISTORY
    assert [s.from_ns for s in est.history] == sorted({s.from_ns for s in est.history})
    clock.step_ns, clock.step_at_ns = 50_000_000, (MAX_HISTORY + 100) * 2 * S
    for k in range(MAX_HISTORY + 100, 2 * MAX_HISTORY + 200):
        est.add(*exchange(clock, k * 2 * S, 50_000, 50_000))
    assert est.restarts == 1
    jumps = [b.offset_ns - a.offset_ns for a, b in zip(est.history, est.history[1:])]
    assert max(jumps) > 49_000_000  # the step's segment survived thinning
    # Reports closer than HISTORY_MIN_NS in relay time replace the newest segment.
    est.add(*exchange(clock, (2 * MAX_HISTORY + 200) * 2 * S, 50_000, 50_000))
    newest = est.history[-1]
    est.add(*exchange(clock, (2 * MAX_HISTORY + 200) * 2 * S + HISTORY_MIN_NS / 2, 20_000, 20_000))
    assert est.history[-2] != newest and est.history[-1].from_ns == newest.from_ns
    assert est.history[-1] != newest


def test_stored_segments_out_of_range_are_named():
    good = Segment(T0, T0, 5_000, 100, 2_000, 300)
    assert segment_fault(good) is None
    assert "offset" in segment_fault(Segment(T0, T0, 10**18))
    assert "drift" in segment_fault(Segment(T0, T0, 0, 10**7))
    assert "negative" in segment_fault(Segment(T0, T0, 0, 0, -1))
    assert "time" in segment_fault(Segment("x", T0, 0))
    assert ClockEstimate(1, 2, 3, 4, at_ns=T0).segment(T0 + 5) == Segment(T0 + 5, T0, 1, 0, 2, 0)


def test_a_history_looked_up_by_corrected_times_gives_each_time_its_own_offset():
    """Exports see timestamps already moved: the same history, indexed on the relay's clock."""
    clock = Clock(-2_000_000_000, 80.0, 30_000_000, 70 * S)
    est, times = run(clock, "udp", 140)
    corr = Correction("estimate", "", tuple(est.history))
    ts = np.linspace(times[0], times[-1], 5000).astype(np.int64)
    moved = corr.correct(ts)
    on_relay = corr.on_relay_clock()
    # Near a segment's start, within the jump of the offset there, a moved time is ambiguous.
    starts = np.array([s.from_ns for s in est.history])
    jumps = np.abs(corr.offsets(starts) - corr.offsets(starts - 1))
    clear = np.all(np.abs(ts[:, None] - starts[None, :]) > jumps[None, :] + 1_000, axis=1)
    assert clear.mean() > 0.95 and est.restarts == 1
    span_s = (times[-1] - times[0]) / S  # the drift's rounding: at most 1 ns per s from the reference
    assert np.abs(on_relay.offsets(moved) - corr.offsets(ts))[clear].max() <= 2 + span_s
    assert np.abs(on_relay.uncertainties(moved) - corr.uncertainties(ts))[clear].max() <= 2


def test_a_history_without_a_current_estimate_still_corrects():
    """A run resumed after a relay restart has its stored history before its first new sample."""
    seg = Segment(T0, T0, 3_000_000, 0, 90_000, 1_000)
    corr = correction_of("estimate", None, {}, history=[seg])
    assert corr.applied == "estimate" and corr.at(T0 + S) == (3_000_000, 91_000)
    assert correction_of("estimate", None, {}).applied == "none"
    assert correction_of("ptp", None, {}, history=[seg]).applied == "ptp"


def test_a_sample_bound_covers_the_drift_while_the_exchange_lasts():
    """All the delay one way (the offset's error is RTT/2) on a clock slow by 400 ppm: the
    measured RTT is short of the true one by the drift over the exchange."""
    clock = Clock(2_000_000, -400.0)
    s = ntp_sample(*exchange(clock, 0, 0, 1e9, hold=0))
    truth = clock.truth_at_node(np.array([s.node_ns]))[0]
    assert abs(s.offset_ns - truth) > (s.rtt_ns + 1) // 2 + TIMESTAMP_FLOOR_NS  # RTT/2 alone falls short
    assert abs(s.offset_ns - truth) <= half_width(s.rtt_ns)


def test_a_runs_correction_is_made_again_only_when_its_clock_or_ptp_state_changed(tmp_path):
    """RelayState.correction gives the one correction_of gives for the run's clock now, made once
    per clock report or PTP state (each push of a run asks for it; a full history makes it slow)."""
    from dcuscope.probes.ship.simnode import header_for
    from dcuscope.relay.live.run import LiveRun
    from dcuscope.relay.live.seqset import SeqSet
    from dcuscope.relay.live.state import RelayState, RunState
    from dcuscope.relay.store.writer import Storage

    header = header_for("n", 1)
    clock = Clock(3_000_000, 10.0)
    rs = RunState(run="run-1", node="n", session=1, header=header, live=LiveRun(header), seqs=SeqSet())
    for mode in ("estimate", "auto"):
        state = RelayState(Storage(tmp_path / f"{mode}.db"), mode)
        for k in range(MAX_HISTORY + 20):
            rs.clock.add(*exchange(clock, k * 2 * S, 50_000, 50_000))
            if k % 50 == 0 or k > MAX_HISTORY + 15:
                made = state.correction(rs)
                assert made is state.correction(rs)  # nothing changed: the same one
                assert made == correction_of(mode, rs.clock.estimate(), rs.ptp, history=rs.clock.history)
        assert len(state.correction(rs).segments) == MAX_HISTORY
        before = state.correction(rs)
        rs.ptp = {"state": "locked", "gm_present": True, "port_state": "SLAVE", "master_offset_ns": 10,
                  "system_clock": {"follows_ptp": True, "synced": True, "by": "phc2sys"}}
        after = state.correction(rs)
        assert after is not before and after == correction_of(mode, rs.clock.estimate(), rs.ptp, history=rs.clock.history)
        assert after.applied == ("ptp" if mode == "auto" else "estimate")
        rs.ptp = {"state": "unavailable"}
        rs.clock = type(rs.clock)(history=list(rs.clock.history[:3]))  # a run's estimator replaced
        assert state.correction(rs).segments == tuple(rs.clock.history[:3])
