"""The compiled delay model (model/c/judge.c) against numpy's, its reference: every figure of
``frame_delays`` equal, on real traces (a graph through a tee, a batching mux), on subsets of their
frames judged by other exit points (as the relay judges a few frames by its run's), and on random
tables that take every path (holes anywhere, graphs with invalid links, no origin)."""

from __future__ import annotations

import numpy as np
import pytest

from dcuscope.model import compiled
from dcuscope.model.delays import STAGE_COLUMNS, frame_delays, frame_delays_numpy
from dcuscope.model.frametable import MISSING, FrameTable, frame_table, frame_table_from_cells
from dcuscope.protocol.events import FRAME_CELLS
from tests.model.planted import planted_core


@pytest.fixture(scope="module")
def core() -> compiled.CompiledCore:
    loaded = compiled.load()
    assert loaded is not None, compiled.unavailable_reason()
    return loaded


def assert_same(a, b) -> None:
    ca, cb = a.chains, b.chains
    for name in ("t_in", "t_out", "passed", "prev", "complete", "end", "has_exit"):
        np.testing.assert_array_equal(getattr(ca, name), getattr(cb, name), err_msg=name)
    for name in STAGE_COLUMNS:
        np.testing.assert_array_equal(a.per_stage[name], b.per_stage[name], err_msg=name)
    np.testing.assert_array_equal(a.delay, b.delay, err_msg="delay")
    np.testing.assert_array_equal(a.glass, b.glass, err_msg="glass")


def subset(table: FrameTable, rows: np.ndarray) -> FrameTable:
    t = FrameTable(table.stages, table.source[rows], table.frame[rows], table.origin[rows], table.origin_stage[rows],
                   table.enter[rows], table.exit[rows], table.ready[rows], table.capture[rows], table.group[rows])
    t.links = table.links
    return t


@pytest.mark.parametrize("name", ["tee", "two"])
def test_on_real_traces_the_compiled_model_gives_numpys_figures(core, real_traces, name):
    trace = real_traces[name]
    table = frame_table(trace.header, trace.events)
    fd = frame_delays(table)
    assert fd.chains.complete.sum() > 100 and np.isfinite(fd.per_stage["service"]).any()
    assert_same(fd, frame_delays_numpy(table))
    rng = np.random.default_rng(1)
    for _ in range(20):
        rows = np.sort(rng.choice(len(table), int(rng.integers(1, 40)), replace=False))
        has_exit = rng.random(len(table.stages)) < 0.5
        part = subset(table, rows)
        assert_same(frame_delays(part, has_exit), frame_delays_numpy(part, has_exit))


def random_table(rng, n: int, s: int) -> FrameTable:
    cells = rng.integers(1, 1 << 40, (n, s, FRAME_CELLS))
    cells[rng.random(cells.shape) < rng.uniform(0.05, 0.6)] = MISSING
    cells[:, :, 5] = rng.integers(-3, 4, (n, s))
    table = frame_table_from_cells([f"s{k}" for k in range(s)], np.zeros(n, np.int32), np.arange(n), cells)
    kind = rng.integers(0, 3)
    if kind == 1:
        table.links = [[int(a), int(b)] for a, b in rng.integers(0, s, (int(rng.integers(1, 2 * s)), 2))]
    elif kind == 2:  # links the graph cannot have, and none it can
        table.links = [[s, 0], [-1, 1], [0, 0]]
    return table


def test_on_random_tables_every_path_gives_numpys_figures(core):
    rng = np.random.default_rng(2)
    for _ in range(400):
        table = random_table(rng, int(rng.integers(1, 30)), int(rng.integers(1, 7)))
        has_exit = None if rng.random() < 0.3 else rng.random(len(table.stages)) < 0.5
        assert_same(frame_delays(table, has_exit), frame_delays_numpy(table, has_exit))


def test_without_the_library_and_when_asked_numpy_judges(monkeypatch, real_traces):
    table = frame_table(real_traces["two"].header, real_traces["two"].events)
    monkeypatch.setattr(compiled, "_loaded", None)
    monkeypatch.setattr(compiled, "_reason", "no compiler, for this test")
    assert compiled.load() is None
    assert_same(frame_delays(table), frame_delays_numpy(table))


def test_a_judge_that_misreads_the_last_stage_is_caught(core, real_traces, tmp_path, monkeypatch):
    """The comparison above can fail: a judge that asks the last stage for an exit it need not have."""
    wrong = planted_core(tmp_path, "judge.c", "(k < s - 1 || j->has_exit[k])", "(k < s || j->has_exit[k])")
    monkeypatch.setattr(compiled, "_loaded", wrong)
    trace = real_traces["two"]
    table = frame_table(trace.header, trace.events)
    with pytest.raises(AssertionError):
        assert_same(frame_delays(table), frame_delays_numpy(table))
