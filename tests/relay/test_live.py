"""The live engine against probes.delays.node_stats over the same events, fed batch by batch."""

from __future__ import annotations

import time

import numpy as np
import pytest

from probes.delays import node_stats
from probes.events import ENTER, EXIT
from probes.simnode import header_for, synth_events
from relay.live import LiveConfig, LiveRun
from tests.probes.synth import pipeline_run
from tests.relay.helpers import assert_stats_equal

T0 = 1_700_000_000_000_000_000


def feed(run: LiveRun, events: np.ndarray, batch: int, maintain_every: int = 1) -> None:
    for k, i in enumerate(range(0, len(events), batch)):
        run.add(events[i:i + batch])
        if k % maintain_every == 0:
            run.maintain()


@pytest.mark.parametrize("batch", [1, 37, 500, 100_000])
def test_matches_node_stats_with_drops(batch):
    header = header_for("n", 3)
    events = synth_events(400, 3, 30.0, T0, drop_rate=0.03, seed=4)
    run = LiveRun(header)
    feed(run, events, batch)
    assert_stats_equal(node_stats(header, events, 7), run.run_stats(7))
    assert run.finalised > 0 and run.late == 0


def test_matches_node_stats_on_batched_mux_with_jitter_and_local_disorder():
    header, events, _ = pipeline_run(600, 4, jitter_ns=5_000_000, batched_mux=True, seed=3)
    events = events[np.argsort(events["ts"], kind="stable")]
    rng = np.random.default_rng(0)
    run = LiveRun(header)
    for i in range(0, len(events), 250):
        chunk = events[i:i + 250]
        run.add(chunk[rng.permutation(len(chunk))])  # order inside a batch must not matter
        run.maintain()
    assert_stats_equal(node_stats(header, events), run.run_stats())


def test_duplicate_tracepoints_keep_the_earliest():
    header = header_for("n", 1)
    events = synth_events(50, 1, 25.0, T0, seed=1)
    dup = events[(events["point"] == EXIT) & (events["stage"] == 2)].copy()
    dup["ts"] += 1_000_000  # a later second sighting at the mux exit
    early = events[(events["point"] == ENTER) & (events["stage"] == 3)].copy()
    early["ts"] -= 500_000  # an earlier second sighting at infer's enter, arriving later
    both = np.concatenate([events, dup, early])
    order = np.argsort(both["ts"], kind="stable")
    run = LiveRun(header, LiveConfig(settle_s=5))
    feed(run, both[order], 64)
    assert_stats_equal(node_stats(header, both), run.run_stats())


def test_incomplete_frames_are_evicted_and_counted():
    header = header_for("n", 2)
    events = synth_events(600, 2, 25.0, T0, drop_rate=0.1, seed=2)  # 24 s of frames
    run = LiveRun(header, LiveConfig(evict_s=2.0))
    feed(run, events, 200)
    ref = node_stats(header, events)
    got = run.run_stats()
    assert run.evicted > 50 and len(run._keys) < 200  # the open table does not grow with the run
    assert got["frames"] == ref["frames"]
    assert_stats_equal(ref, got)


def test_late_events_for_finalised_frames_are_ignored_and_counted():
    header = header_for("n", 1)
    events = synth_events(200, 1, 25.0, T0, seed=5)
    run = LiveRun(header, LiveConfig(settle_s=0.5))
    feed(run, events, 100)
    before = run.run_stats()
    late = events[(events["frame"] < 10) & (events["stage"] == 3)].copy()
    late["ts"] -= 1  # would change those frames' infer delay if it were merged
    run.add(late)
    run.maintain()
    assert run.late == len(late)
    assert_stats_equal(before, run.run_stats())


def test_window_covers_recent_frames_only():
    header = header_for("n", 1)
    events = synth_events(500, 1, 10.0, T0, seed=6)  # 50 s at 10 fps
    run = LiveRun(header, LiveConfig(window_s=10.0))
    feed(run, events, 300)
    w = run.window_stats()
    assert 95 <= w["frames"]["complete"] <= 101
    assert w["fps"]["0"] == pytest.approx(10.0, rel=0.02)
    assert w["frame"]["count"] == w["frames"]["complete"]
    assert run.run_stats()["frames"]["complete"] == 500


def test_visible_frames_and_bottleneck():
    header = header_for("n", 2)
    events = synth_events(100, 2, 25.0, T0, seed=7)
    run = LiveRun(header)
    feed(run, events, 120)
    assert run.visible == 200
    assert run.recent(since=190, limit=5, newest=True)[0].tolist() == [196, 197, 198, 199, 200]
    n, fd = run.recent(since=190, limit=5)
    assert n.tolist() == [191, 192, 193, 194, 195] and fd.chains.complete.all()
    for stats in (run.run_stats(), run.window_stats()):
        b = stats["bottleneck"]
        assert b["stage"] == "infer" and 0.5 < b["share"] < 1.0
        assert b["share"] == stats["stages"]["infer"]["share"]


def test_throughput_is_vectorised():
    header = header_for("n", 4)
    events = synth_events(5000, 4, 30.0, T0, drop_rate=0.01, seed=8)  # 240k events
    run = LiveRun(header)
    t = time.perf_counter()
    feed(run, events, 2000, maintain_every=5)
    rate = len(events) / (time.perf_counter() - t)
    assert rate > 100_000, f"{rate:.0f} events/s"


def test_open_frames_are_bounded_when_timestamps_stand_still():
    header = header_for("n", 1)
    events = synth_events(3000, 1, 25.0, T0, seed=9)
    events = events[events["stage"] < 3]  # nothing ever completes
    events["ts"] = T0  # and node time never moves
    run = LiveRun(header, LiveConfig(max_open_frames=500))
    feed(run, events, 1000)
    assert len(run._keys) <= 500 and run.evicted >= 2500
    assert run.run_stats()["frames"] == {"complete": 0, "incomplete": 3000}
