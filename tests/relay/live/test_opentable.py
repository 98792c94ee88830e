"""The live engine's table of open frames: rows found by key as a dict would, whatever opens and closes."""

from __future__ import annotations

import numpy as np

from dcuscope.model.frametable import MISSING
from dcuscope.protocol.events import FRAME_CELLS
from dcuscope.relay.live.opentable import OpenTable


def test_rows_are_found_by_key_through_opens_and_closes_and_keep_their_cells():
    rng = np.random.default_rng(5)
    table, model = OpenTable(stages=3), {}  # key -> (last, cells[0, 0, 0])
    next_key = 0
    for step in range(300):
        # Open a few keys, interleaved with the open ones (two sources, as a paced node's).
        new = np.unique(rng.integers(0, next_key + 40, 8))
        new = new[~np.isin(new, list(model))]
        next_key += 20
        table.open(new)
        rows, found = table.locate(new)
        assert found.all() and (table.cells[rows] == MISSING).all() and not table.shown[rows].any()
        table.last[rows] = new * 10 + step
        table.cells[rows, 0, 0] = new
        model.update({int(k): (int(k) * 10 + step, int(k)) for k in new})
        if step % 7 == 6:  # finalisation: about half close
            keep = rng.random(table.n) < 0.5
            for k in table.keys[~keep]:
                del model[int(k)]
            table.keep(keep)
        assert table.n == len(model) and sorted(table.keys.tolist()) == sorted(model)
        keys = np.array(sorted(model) + [-5, next_key + 10_000], np.int64)
        rows, found = table.locate(keys)
        assert found.tolist() == [True] * len(model) + [False, False]
        assert table.keys[rows[found]].tolist() == sorted(model)
        assert table.last[rows[found]].tolist() == [model[k][0] for k in sorted(model)]
        assert table.cells[rows[found], 0, 0].tolist() == sorted(model)
    assert table.cells.shape[1:] == (3, FRAME_CELLS)


def test_memory_goes_back_when_most_frames_close():
    table = OpenTable(stages=8)
    table.open(np.arange(100_000, dtype=np.int64))
    big = table.nbytes
    table.keep(np.arange(100_000) < 100)
    assert table.n == 100 and table.nbytes < big / 100
    rows, found = table.locate(np.array([5, 99, 100]))
    assert found.tolist() == [True, True, False] and table.keys[rows[:2]].tolist() == [5, 99]
