"""The --clock-offset-ms / --clock-drift-ppm testing aid: one pretend clock for a node's events
(capture times, the camera's clock, left alone) and its clock exchanges."""

from __future__ import annotations

import time

import numpy as np

from dcuscope.core.clocks import CLOCKS, PretendClock
from dcuscope.probes.ship.shifted import Shifted
from dcuscope.protocol.events import CAPTURE, ORIGIN
from tests.probes.synth import T0, _events


class _Keep:
    def start(self, header):
        pass

    def write(self, events):
        self.events = events

    def close(self, dropped):
        pass


def test_events_move_by_the_offset_plus_the_drift_since_the_start():
    pretend = PretendClock(37_000_000, 50.0, start_ns=T0)
    inner = _Keep()
    ts = np.array([T0, T0 + 10**9, T0 + 60 * 10**9])
    src = np.zeros(3, np.int32)
    events = np.concatenate([_events(ts, src, np.arange(3), 0, ORIGIN), _events(ts, src, np.arange(3), 0, CAPTURE)])
    Shifted(inner, pretend).write(events)
    got = inner.events
    # 50 ppm: 50 us after one second, 3 ms after a minute.
    assert (got["ts"][got["point"] == ORIGIN] - ts).tolist() == [37_000_000, 37_050_000, 40_000_000]
    assert got["ts"][got["point"] == CAPTURE].tolist() == ts.tolist()
    assert [pretend.of(int(t)) for t in ts] == got["ts"][got["point"] == ORIGIN].tolist()


def test_now_reads_the_probes_clock_through_the_pretence():
    pretend = PretendClock(-2_500_000_000, -100.0, CLOCKS["monotonic"])
    before = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
    now = pretend.now()
    after = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
    assert pretend.of(before) <= now <= pretend.of(after)
    assert abs(now - (before - 2_500_000_000)) < 10_000_000
