"""A node with a skewed clock: the relay recovers the skew within its stated uncertainty and,
under --clock estimate, corrected cross-node times agree; under --clock ptp nothing is corrected."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.relay.helpers import RelayProcess, finish_node, get_json, start_node

SKEW_NS = 37_000_000


@pytest.mark.parametrize("mode", ["estimate", "ptp"])
def test_injected_skew_is_recovered_and_corrected(tmp_path, mode):
    relay = RelayProcess(tmp_path / "relay.db", clock=mode)
    try:
        t0 = time.clock_gettime_ns(time.CLOCK_REALTIME) + 500_000_000
        # The same seed and start: both nodes see the very same frames at the very same true times.
        common = dict(frames=150, sources=2, fps=50, paced=True, t0_ns=t0, seed=9)
        a = start_node(relay.url, "A", tmp_path / "a.npz", **common)
        b = start_node(relay.url, "B", tmp_path / "b.npz", offset_ns=SKEW_NS, **common)
        finish_node(a, 60), finish_node(b, 60)
        nodes = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}
        ca, cb = nodes["A"]["clock"], nodes["B"]["clock"]
        assert ca["samples"] >= 8 and cb["samples"] >= 8
        assert abs(cb["offset_ns"] - SKEW_NS) <= cb["uncertainty_ns"], cb
        assert abs(ca["offset_ns"]) <= ca["uncertainty_ns"], ca
        assert cb["uncertainty_us"] < 5_000  # loopback: well under the skew itself

        fa = get_json(f"{relay.url}/api/frames?node=A&limit=2000")
        fb = get_json(f"{relay.url}/api/frames?node=B&limit=2000")
        assert len(fa["frames"]) == len(fb["frames"]) == 300
        key = lambda f: (f["source"], f["frame"])  # noqa: E731
        by_a = {key(f): f for f in fa["frames"]}

        def times(f):
            return np.array([f["origin"]] + [t for t in f["enter"] + f["exit"] if t is not None], np.int64)

        diffs = np.array([times(f) - times(by_a[key(f)]) for f in fb["frames"]])
        if mode == "estimate":
            assert fb["clock"] == "estimate" and abs(fb["correction_ns"] - SKEW_NS) <= fb["uncertainty_ns"]
            # Each frame corrected by the estimate in force at its time, within that estimate's bound.
            bars = np.array([f["clock_uncertainty_ns"] + by_a[key(f)]["clock_uncertainty_ns"] for f in fb["frames"]])
            assert (np.abs(diffs).max(axis=1) <= bars).all()
            # A cross-node delay (B's sink enter - A's origin) equals the true one within the error bars.
            f_b, f_a = fb["frames"][-1], by_a[key(fb["frames"][-1])]
            true_delay = f_a["enter"][-1] - f_a["origin"]
            assert abs((f_b["enter"][-1] - f_a["origin"]) - true_delay) <= bars[-1]
        else:
            assert fb["clock"] == "ptp" and fb["correction_ns"] == 0
            assert (diffs == SKEW_NS).all()
    finally:
        relay.stop()
