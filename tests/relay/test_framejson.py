"""Frames as the API carries them: node timestamps corrected per timestamp, the capture time (the
camera's clock) left alone, glass-to-glass taken from the corrected end."""

from __future__ import annotations

import numpy as np

from relay.clock.correction import Correction, Segment
from relay.live.framejson import frame_dicts
from tests.probes.synth import T0
from tests.relay.test_moments import node_run

PERIOD = 100_000_000


def test_node_times_are_corrected_the_capture_is_not_and_glass_uses_the_corrected_end():
    captures = T0 + np.arange(5, dtype=np.int64) * PERIOD
    offset, drift_ppb = 37_000_000, 50_000  # a node 37 ms ahead, gaining 50 ppm
    _, fd = node_run("dcu", captures, delay_ns=20_000_000, offset_ns=offset)
    corr = Correction("estimate", "test", (Segment(T0, T0, offset, drift_ppb=drift_ppb, uncertainty_ns=5_000),))
    frames = frame_dicts(np.arange(1, 6), fd, corr)
    assert [f["capture"] for f in frames] == captures.tolist()
    for f, cap, origin, end in zip(frames, captures, fd.table.origin, fd.chains.end):
        off_origin = offset + round(drift_ppb * (origin - T0) / 1e9)
        off_end = offset + round(drift_ppb * (end - T0) / 1e9)
        assert f["origin"] == origin - off_origin and f["end"] == end - off_end
        assert f["clock_ns"] == off_origin and f["clock_uncertainty_ns"] == 5_000
        assert abs(f["glass_ms"] - (end - off_end - cap) / 1e6) < 1e-6
        assert abs(f["glass_ms"] - 50.0 + (off_end - offset) / 1e6) < 1e-6  # 30 ms to origin + 20 ms, true clock
