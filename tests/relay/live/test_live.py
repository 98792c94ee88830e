"""The live engine against model.delays.node_stats over the same events, fed batch by batch."""

from __future__ import annotations

import time

import numpy as np
import pytest

from dcuscope.model.delays import frame_delays, node_stats
from dcuscope.model.frametable import frame_table
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.events import DROP, ENTER, EVENT_DTYPE, EXIT, FACT, FACT_LOST_UPSTREAM, LATE, TraceHeader
from dcuscope.protocol.wire import SOURCE_LIMIT
from dcuscope.relay.live.run import LiveConfig, LiveRun
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
    assert run.evicted > 50 and run.open_count < 200  # the open table does not grow with the run
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
    # It ends at the present: the node's newest event, later while the node is silent, never before it.
    assert run.newest <= w["end_ns"] <= run.present_ns()
    assert run.present_ns(bound_ns=run.newest - 1) == run.newest
    # A run silent for longer than the window has nothing in it.
    gone = run.window_stats(run.newest + 10_500_000_000)
    assert gone["frames"] == {"complete": 0, "incomplete": 0} and gone["fps"] == {"0": 0.0}


def test_the_windows_sources_count_the_window_as_its_frames_do():
    """The statistics panel shows the window's sources beside its frames: both over the last window_s, not
    the sources over the whole run (871 delivered beside 102 frames)."""
    header = header_for("n", 2)
    events = synth_events(500, 2, 10.0, T0, seed=6)  # 50 s at 10 fps a source
    # Two drops, one long before the window and one within it; a counter fact rising in both.
    extra = np.zeros(4, EVENT_DTYPE)
    extra["ts"] = [T0 + 5_000_000_000, T0 + 45_000_000_000, T0 + 5_000_000_000, T0 + 45_000_000_000]
    extra["point"], extra["source"] = [DROP, DROP, FACT, FACT], 0
    extra["code"] = [LATE, LATE, FACT_LOST_UPSTREAM, FACT_LOST_UPSTREAM]
    extra["frame"] = [3, 450, 7, 10]  # a drop's frame; a fact's cumulative value
    events = np.concatenate([events, extra])
    events = events[np.argsort(events["ts"], kind="stable")]
    run = LiveRun(header, LiveConfig(window_s=10.0))
    feed(run, events, 300)
    w, whole = run.window_stats(), run.run_stats()
    assert whole["sources"]["0"]["delivered"] == 500 and whole["sources"]["0"]["dropped"] == {"late": 2}
    assert whole["sources"]["0"]["lost_upstream"] == 10
    delivered = sum(v["delivered"] for v in w["sources"].values())
    # Origins are binned by 0.1 s and frames judged by their chain's end: a frame or two a source apart.
    assert w["frames"]["complete"] - 4 <= delivered <= w["frames"]["complete"] + 4, (delivered, w["frames"])
    assert 190 <= delivered <= 206
    assert w["sources"]["0"]["dropped"] == {"late": 1} and w["sources"]["0"]["lost_upstream"] == 3
    assert w["sources"]["1"]["dropped"] == {} and w["sources"]["1"]["lost_upstream"] == 0
    assert whole["span_s"] == pytest.approx(50.0, abs=0.5)


def _window_by_the_model(header, events, end_ns: int, window_s: float) -> dict:
    """node_stats over the frames whose chain (judged over every event) ended in the window."""
    fd = frame_delays(frame_table(header, events))
    inside = fd.chains.complete & (fd.chains.end >= end_ns - int(window_s * 1e9))
    ids = set(zip(fd.table.source[inside].tolist(), fd.table.frame[inside].tolist()))
    return node_stats(header, events[[(s, f) in ids for s, f in zip(events["source"].tolist(), events["frame"].tolist())]])


@pytest.mark.parametrize("exits_from", [None, 240])
def test_the_window_summarises_kept_frames_from_their_values_by_the_exit_points_seen_since(exits_from):
    """The window's frames finalised earlier are summarised from the values kept when they were
    finalised, not judged again from their events; yet by the exit points the run has seen since:
    the sink's exit, first seen at frame ``exits_from``, makes every frame without one incomplete,
    kept ones too, as the model judges them over every event."""
    header = header_for("n", 1)
    events = synth_events(300, 1, 10.0, T0, seed=9)  # 30 s at 10 fps
    sink = len(header.stages) - 1
    if exits_from is not None:
        late = events[(events["stage"] == sink) & (events["frame"] >= exits_from)].copy()
        late["point"], late["ts"] = EXIT, late["ts"] + 1_000_000
        events = np.concatenate([events, late])
        events = events[np.argsort(events["ts"], kind="stable")]
    run = LiveRun(header, LiveConfig(window_s=10.0))
    feed(run, events, 40)
    end = run.newest
    window = run.window_stats(end)
    assert run._ring["end"].n > 0 and (run._ring["end"].view >= end - 10_000_000_000).any()  # kept frames in it
    assert len({kept.n for kept in run._ring.values()}) == 1  # a row a frame in every kept column
    expected = _window_by_the_model(header, events, end, 10.0)
    for key in ("stages", "gaps", "frame", "bottleneck", "fps"):
        assert window[key] == expected[key], key
    assert window["frames"]["complete"] == expected["frames"]["complete"] == (100 if exits_from is None else 60)


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
    assert run.open_count <= 500 and run.evicted >= 2500
    assert run.run_stats()["frames"] == {"complete": 0, "incomplete": 3000}


def test_a_paper_sized_run_stays_exact_on_the_smallest_default_share():
    # 4 sources, 11 stages, 1,200 frames with a few hundred open at once, on a 256 MiB relay
    # holding 64 runs (4 MiB each): nothing evicted, every figure equal to node_stats.
    header = header_for("n", 4)
    events = synth_events(300, 4, 30.0, T0, drop_rate=0.02, seed=6)
    run = LiveRun(header, budget=4 * 2**20)
    feed(run, events, 2000, maintain_every=4)
    assert run.open_cap > 1000 and run.evicted == 0
    assert_stats_equal(node_stats(header, events), run.run_stats())
    assert run.nbytes <= 4 * 2**20


def test_a_batch_of_more_new_frames_than_fit_opens_only_its_newest():
    stages = 64
    header = TraceHeader(node="n", clock="realtime", stages=[f"s{i}" for i in range(stages)])
    n = 65536
    ev = np.zeros(n, EVENT_DTYPE)
    ev["ts"], ev["frame"], ev["stage"], ev["point"] = T0 + np.arange(n), np.arange(n), np.arange(n) % stages, ENTER
    budget = 8 * 2**20
    run = LiveRun(header, budget=budget)
    cap = run.open_cap
    assert cap < 2000  # frames cost bytes: 64 stages x 6 cells
    run.add(ev)
    run.maintain()
    assert run.open_count == cap and run.evicted == n - cap
    assert run.open_keys().min() == n - cap  # the newest frames are those kept
    assert run.nbytes <= budget
    late = ev[:10].copy()  # events of frames evicted on arrival are late now
    run.add(late)
    run.maintain()
    assert run.late == 10 and run.run_stats()["frames"] == {"complete": 0, "incomplete": n}


def test_a_smaller_share_spills_exact_values_and_keeps_counts():
    header = header_for("n", 2)
    events = synth_events(600, 2, 30.0, T0, seed=7)
    run = LiveRun(header)
    feed(run, events, 500)
    before = run.run_stats()
    assert before["percentile_error"] == 0.0
    run.set_budget(256 * 1024)
    assert run.nbytes <= 256 * 1024
    after = run.run_stats()
    assert after["percentile_error"] > 0 and after["frames"] == before["frames"]
    assert after["frame"]["count"] == before["frame"]["count"] and after["frame"]["max_ms"] == before["frame"]["max_ms"]


def test_far_source_ids_cost_no_memory_and_their_number_is_bounded():
    header = header_for("n", 1)
    run = LiveRun(header)
    held = run.nbytes
    ev = synth_events(5, 1, 25.0, T0, seed=1)
    ev["source"] = SOURCE_LIMIT - 1
    assert run.admit_sources(ev["source"], 2) == 1
    feed(run, ev, 100)
    assert run.nbytes - held < 64 * 1024
    assert run.run_stats()["frames"]["complete"] == 5 and list(run.run_stats()["fps"]) == ["0", str(SOURCE_LIMIT - 1)]
    assert run.admit_sources(np.array([1, 2, SOURCE_LIMIT - 1]), 2) == 3  # refused: nothing noted
    assert run.admit_sources(np.array([7]), 2) == 2


def test_each_finalised_frame_is_told_once_with_the_figures_the_statistics_use():
    header = header_for("n", 3)
    events = synth_events(400, 3, 30.0, T0, drop_rate=0.03, seed=4)
    run = LiveRun(header)
    told: list[tuple] = []
    run.on_finalise = lambda fd, values: told.append((fd, values))
    feed(run, events, 97)
    keys = np.concatenate([fd.table.source.astype(np.int64) << 32 | fd.table.frame for fd, _ in told])
    assert len(keys) == len(np.unique(keys)) == run.finalised  # every finalised frame, once
    assert all(fd.chains.complete.all() for fd, _ in told)
    frame_ms = np.concatenate([v.frame for _, v in told]) / 1e6
    finalised = run._frame_values.summary(np.zeros(0))  # the whole-run statistics' finalised part
    assert finalised["count"] == len(frame_ms)
    assert np.isclose(finalised["mean_ms"], frame_ms.mean()) and np.isclose(finalised["max_ms"], frame_ms.max())


def test_a_finished_run_finalises_its_last_complete_frames_and_its_statistics_stay():
    """The node's time stops at its end: without ``finish`` its last ``settle_s`` of complete frames
    would never reach the exporters (``on_finalise``)."""
    header = header_for("n", 2)
    events = synth_events(300, 2, 30.0, T0, drop_rate=0.03, seed=5)
    run = LiveRun(header)
    told: list[int] = []
    run.on_finalise = lambda fd, values: told.append(len(values.frame))
    feed(run, events, 97)
    before = run.run_stats()
    complete = before["frames"]["complete"]
    assert 0 < run.finalised < complete  # the last seconds wait for stragglers
    run.finish()
    assert run.finalised == sum(told) == complete
    assert_stats_equal(before, run.run_stats())
    run.finish()
    assert sum(told) == complete  # once only


@pytest.mark.parametrize("batch, maintain_every", [(37, 1), (400, 3)])
def test_pushed_columns_are_the_frames_recent_gives(batch, maintain_every):
    """The pushes take each complete frame's columns as they were judged when it was shown
    (``recent_columns``), not derived again: they equal those of the same frames from ``recent``,
    clock correction and all, with drops, disorder and a partial last page."""
    from dcuscope.relay.api.interest import MAX_FRAMES
    from dcuscope.relay.clock.correction import Correction, Segment
    from dcuscope.relay.live import framepack
    from dcuscope.relay.live.run import PUSHED_FRAMES

    header, events, _ = pipeline_run(300, 3, jitter_ns=5_000_000, batched_mux=True, seed=8)
    events = events[np.argsort(events["ts"], kind="stable")]
    run = LiveRun(header)
    feed(run, events, batch, maintain_every)
    run.maintain()
    stages = len(header.stages)
    corr = Correction("estimate", "test", (Segment(T0, T0, 37_000, drift_ppb=20_000, uncertainty_ns=5_000),))
    assert PUSHED_FRAMES >= MAX_FRAMES  # a push asks for MAX_FRAMES at most
    for since, limit in ((0, MAX_FRAMES), (run.visible - 50, 20), (run.visible, 5)):
        n, fd = run.recent(since, limit, newest=True)
        want = framepack.columns(n, fd, corr)
        got = framepack.corrected(*run.recent_columns(since, limit), corr, stages)
        assert got[0].shape[1] == len(n) == min(limit, run.visible - max(since, 0))
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    assert run.visible > 500


def test_whole_run_statistics_of_many_runs_share_one_share_of_the_relays_time():
    """Unless asked fresh, a run's whole-run statistics wait until their last cost, times the
    runs kept this way, is within STATS_SHARE of the time since: 32 runs of a long day cost what
    one does, not 32 times more; the HTTP API's fresh ones are always computed."""
    from dcuscope.relay.live.state import STATS_SHARE, WholeRunStats

    events = synth_events(200, 2, 30.0, T0, seed=2)
    run = LiveRun(header_for("n", 2))
    run.add(events[:1000])
    whole = WholeRunStats()
    first = whole.get(run, 0, fresh=False, runs=32)
    run.add(events[1000:])
    whole.at, whole.cost = time.monotonic() - 1.0, 0.01  # 1 s ago, at 10 ms
    assert 32 * 0.01 / STATS_SHARE > 1.0 > 0.01 / STATS_SHARE
    assert whole.get(run, 0, fresh=False, runs=32) is first
    second = whole.get(run, 0, fresh=False, runs=1)
    assert second is not first and second["frames"]["complete"] > first["frames"]["complete"]
    run.add(events[:10])
    assert whole.get(run, 0, fresh=True, runs=32) is not second


def test_a_silent_runs_window_empties_however_long_its_last_one_took():
    """A window waits its turn (its last cost, times the runs, within WINDOW_SHARE), except once every
    event of its run is older than it: then it is empty, said at once, and kept until new events come."""
    from dcuscope.relay.clock.correction import NO_CORRECTION
    from dcuscope.relay.live.state import WindowStats

    run = LiveRun(header_for("n", 1), LiveConfig(window_s=0.05))
    run.add(synth_events(20, 1, 1000.0, T0, seed=3))  # 20 ms of frames
    window = WindowStats()
    full = window.get(run, NO_CORRECTION, fresh=False)
    assert full["frames"]["complete"] > 10
    window.cost = 1000.0  # its next turn would come in hours
    time.sleep(0.06)  # silent for longer than the window
    empty = window.get(run, NO_CORRECTION, fresh=False)
    assert empty["frames"] == {"complete": 0, "incomplete": 0} and empty["fps"] == {"0": 0.0}
    assert window.settled(run) and window.get(run, NO_CORRECTION, fresh=True) is empty


def test_a_window_up_to_a_second_old_serves_the_fleets_rows_and_a_push_gets_a_new_one():
    """The statistics push asks for a window at most 0.5 s old, the fleet's rows (rebuilt once a second)
    for one at most a second old: made 0.7 s ago, with new events since, the rows take it as it is and
    the push gets a new one, which the rows then share."""
    from dcuscope.relay.clock.correction import NO_CORRECTION
    from dcuscope.relay.live.state import WindowStats

    run = LiveRun(header_for("n", 1))
    events = synth_events(200, 1, 1000.0, T0, seed=4)
    run.add(events[:100])
    window = WindowStats()
    first = window.get(run, NO_CORRECTION, fresh=False)
    run.add(events[100:])
    window.at, window.cost = time.monotonic() - 0.7, 0.0
    assert window.get(run, NO_CORRECTION, fresh=False, max_age_s=1.0) is first
    pushed = window.get(run, NO_CORRECTION, fresh=False)
    assert pushed is not first and pushed["frames"]["complete"] > first["frames"]["complete"]
    assert window.get(run, NO_CORRECTION, fresh=False, max_age_s=1.0) is pushed


def test_runs_maintained_together_show_and_state_exactly_what_each_alone_does():
    """The pusher judges the frames of every run of one graph in one pass (maintain_all): runs of
    the same graph, and one of another, fed alike batch by batch, show the same frames with the same
    columns, and end with the same statistics as twins maintained one by one."""
    from dcuscope.relay.live.run import maintain_all

    feeds = [(header_for(f"n{k}", 2), synth_events(300, 2, 30.0, T0 + k * 7_000_000, drop_rate=0.05 * k, seed=k))
             for k in range(3)]
    header, events, _ = pipeline_run(300, 4, jitter_ns=5_000_000, batched_mux=True, seed=5)
    feeds.append((header, events[np.argsort(events["ts"], kind="stable")]))
    together = [LiveRun(h) for h, _ in feeds]
    alone = [LiveRun(h) for h, _ in feeds]
    for i in range(0, max(len(e) for _, e in feeds), 211):
        for (_, ev), a, b in zip(feeds, together, alone):
            a.add(ev[i:i + 211])
            b.add(ev[i:i + 211])
        maintain_all(together)
        for a, b in zip(together, alone):
            b.maintain()
            assert a.visible == b.visible and a.finalised == b.finalised and a.open_count == b.open_count
    for a, b in zip(together, alone):
        for got, want in zip(a.recent_columns(0, 500), b.recent_columns(0, 500)):
            np.testing.assert_array_equal(got, want)
        assert_stats_equal(b.run_stats(), a.run_stats())
        assert a.visible > 300 and a.finalised > 0
