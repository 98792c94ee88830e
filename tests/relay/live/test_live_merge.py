"""The live engine's compiled merge (model/c/merge.c) against its numpy merge and against the
offline delay model, on real traces and on synthetic runs that take every path of the merge."""

from __future__ import annotations

import logging
import subprocess
import sys

import numpy as np
import pytest

from dcuscope.model import compiled as cmerge
from dcuscope.model.delays import node_stats
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.events import DROP, ENTER, EXIT, FACT, FACT_LOST_UPSTREAM
from dcuscope.relay.live.run import PUSHED_FRAMES, LiveConfig, LiveRun
from tests.conftest import cli_env
from tests.model.planted import planted_core
from tests.probes.synth import pipeline_run
from tests.relay.helpers import assert_stats_equal

T0 = 1_700_000_000_000_000_000
def both(header, config: LiveConfig = LiveConfig()) -> tuple[LiveRun, LiveRun]:
    compiled = LiveRun(header, config)
    assert compiled._open.compiled, cmerge.unavailable_reason()
    return compiled, LiveRun(header, config, compiled=False)


def feed_alike(runs: tuple[LiveRun, LiveRun], batches: list[np.ndarray]) -> None:
    """Each batch to both runs, a tick after each: the same frames shown at every tick, with the same
    pushed columns (in another order: the compiled merge opens frames in event order)."""
    for batch in batches:
        shown = []
        for run in runs:
            since = run.visible
            run.add(batch)
            run.maintain()
            shown.append(run.recent_columns(since, PUSHED_FRAMES))
        (ia, fa), (ib, fb) = shown
        oa, ob = np.lexsort((ia[2], ia[1])), np.lexsort((ib[2], ib[1]))
        assert np.array_equal(ia[1:, oa], ib[1:, ob]) and np.array_equal(fa[:, oa], fb[:, ob], equal_nan=True)
    a, b = runs
    assert [(r.visible, r.finalised, r.evicted, r.late, r.newest, r.open_count) for r in runs][0] == \
           (b.visible, b.finalised, b.evicted, b.late, b.newest, b.open_count)
    assert sorted(a.open_keys().tolist()) == sorted(b.open_keys().tolist())


def chunks(events: np.ndarray, size: int) -> list[np.ndarray]:
    return [events[i:i + size] for i in range(0, len(events), size)]


@pytest.mark.parametrize("name", ["tee", "two"])
def test_on_real_traces_the_compiled_merge_gives_the_offline_statistics(real_traces, name):
    trace = real_traces[name]
    assert len(trace.events) > 1000
    runs = both(trace.header)
    feed_alike(runs, chunks(trace.events, 97))
    offline = node_stats(trace.header, trace.events, trace.dropped)
    for run in runs:
        run.finish()
        assert_stats_equal(offline, run.run_stats(trace.dropped))
    assert runs[0].run_stats(trace.dropped) == runs[1].run_stats(trace.dropped)
    end = runs[0].newest  # by default the window ends at the present, which moves between two calls
    assert runs[0].window_stats(end) == runs[1].window_stats(end)


def test_drops_duplicates_disorder_and_late_events_leave_both_merges_alike():
    header, events, _ = pipeline_run(600, 4, jitter_ns=5_000_000, batched_mux=True, seed=3)
    events = events[np.argsort(events["ts"], kind="stable")]
    again = events[(events["point"] == EXIT) | (events["point"] == ENTER)][::7].copy()
    again["ts"] += 300_000  # tracepoints that saw a frame twice: the cell keeps the earliest
    mixed = np.concatenate([events, again])
    mixed = mixed[np.argsort(mixed["ts"], kind="stable")]
    rng = np.random.default_rng(1)
    batches = [c[rng.permutation(len(c))] for c in chunks(mixed, 250)]  # order inside a batch must not matter
    runs = both(header, LiveConfig(settle_s=0.2, evict_s=0.5))
    feed_alike(runs, [*batches, batches[0], batches[1]])  # the first batches again, late
    assert runs[0].late > 0 and runs[0].finalised > 0
    assert runs[0].run_stats() == runs[1].run_stats()
    window = [run.window_stats(runs[0].newest) for run in runs]  # its sources counted per bin, compiled and not
    assert window[0] == window[1]


def test_a_table_at_its_cap_evicts_as_numpy_does_through_the_hash():
    """Batches that could take the open table past its cap take the numpy merge (eviction first) on the
    compiled table: its keys are then found and opened through the hash."""
    header = header_for("n", 3)
    events = synth_events(400, 3, 30.0, T0, drop_rate=0.2, seed=5)
    runs = both(header, LiveConfig(max_open_frames=100, settle_s=0.2, evict_s=30))
    feed_alike(runs, chunks(events, 61))
    assert runs[0].evicted > 0 and runs[0].finalised > 0, (runs[0].evicted, runs[0].finalised)
    assert runs[0].run_stats(0) == runs[1].run_stats(0)


def test_origins_drops_and_counted_facts_fill_both_windows_alike():
    """The compiled count of a batch's origins per source and bin, and numpy's, give the window and the
    run the same sources table, drops and facts included."""
    header = header_for("n", 2)
    events = synth_events(300, 2, 30.0, T0, seed=6)
    extra = np.zeros(40, events.dtype)
    extra["ts"] = np.linspace(events["ts"][0], events["ts"][-1], 40).astype(np.int64)
    extra["source"] = np.arange(40) % 2
    extra["point"] = np.where(np.arange(40) % 3 == 0, FACT, DROP)
    extra["code"] = np.where(extra["point"] == FACT, FACT_LOST_UPSTREAM, 3)
    extra["frame"] = np.where(extra["point"] == FACT, np.arange(40) * 2, 0)
    mixed = np.concatenate([events, extra])
    runs = both(header)
    feed_alike(runs, chunks(mixed[np.argsort(mixed["ts"], kind="stable")], 90))
    assert runs[0].run_stats() == runs[1].run_stats()
    window = [run.window_stats(runs[0].newest) for run in runs]
    assert window[0] == window[1]
    sources = window[0]["sources"]
    assert all(s["dropped"].get("queue full") and s["lost_upstream"] > 0 and s["delivered"] > 0 for s in sources.values())


def test_without_a_compiler_the_relay_says_why_once_and_merges_with_numpy(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(cmerge, "_loaded", None)
    monkeypatch.setattr(cmerge, "_reason", None)
    monkeypatch.setattr(cmerge, "LIBRARY", tmp_path / "_build" / cmerge.LIBRARY.name)
    monkeypatch.setenv("CC", "false")
    with caplog.at_level(logging.WARNING, logger=cmerge.__name__):
        assert cmerge.load() is None and cmerge.load() is None
    reason = cmerge.unavailable_reason()
    assert reason.startswith("compiling libdcuscope_core.so failed")
    assert [r.getMessage() for r in caplog.records] == [f"compiled core unavailable ({reason}): batches are decoded, paired and "
                                                       f"judged with numpy, ~1 µs more per event"]
    header = header_for("n", 2)
    run = LiveRun(header)
    assert not run._open.compiled
    events = synth_events(100, 2, 30.0, T0, seed=2)
    for c in chunks(events, 50):
        run.add(c)
        run.maintain()
    assert_stats_equal(node_stats(header, events), run.run_stats())


def test_the_build_and_check_commands():
    for command, says in (("build", cmerge.LIBRARY.name), ("check", "compiled core loaded")):
        done = subprocess.run([sys.executable, "-m", "dcuscope.model.compiled", command], env=cli_env(),
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 0 and says in done.stdout, done.stderr
    done = subprocess.run([sys.executable, "-m", "dcuscope.model.compiled"], env=cli_env(), capture_output=True, text=True)
    assert done.returncode == 2 and "usage" in done.stderr


def test_a_merge_keeping_a_cells_latest_time_is_caught(tmp_path, monkeypatch):
    """The comparison above can fail: a compiled merge that keeps each cell's latest time, not its
    earliest, shows other frames than numpy's on the same real batches."""
    monkeypatch.setattr(cmerge, "_loaded", planted_core(tmp_path, "merge.c", "e->ts < c[e->point]", "e->ts > c[e->point]"))
    header, events, _ = pipeline_run(200, 2, seed=8)
    events = events[np.argsort(events["ts"], kind="stable")]
    again = events[events["point"] == EXIT][::5].copy()
    again["ts"] += 300_000
    mixed = np.concatenate([events, again])
    with pytest.raises(AssertionError):
        feed_alike(both(header), chunks(mixed[np.argsort(mixed["ts"], kind="stable")], 100))
