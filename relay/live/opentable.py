"""The open frames of a live run: rows in the order the frames opened, found by key through a sorted index.

A paced node opens a few frames per batch while hundreds wait to settle. Kept sorted by key, the
table was copied whole and sorted again on every batch that opened one; here opening appends rows
(amortised, as :class:`dcuscope.relay.live.run.Grow`) and re-sorts only the index of keys, and only
:meth:`OpenTable.keep` (finalisation and eviction, a few times a second) moves rows.

Rows are in opening order, not key order: what reads the table takes frames as a set.
"""

from __future__ import annotations

import numpy as np

from dcuscope.probes.trace.events import FRAME_CELLS
from dcuscope.probes.trace.frametable import MISSING

MIN_ROWS = 64


class OpenTable:
    """Open frames of one run: per row its key (``source << KEY_SHIFT | frame``), cells (the earliest
    timestamp of each (stage, point)), newest event time, whether it was shown, and where its chain ended."""

    def __init__(self, stages: int) -> None:
        self._s = stages
        self.n = 0
        self._alloc(MIN_ROWS)
        self._sorted = np.zeros(0, np.int64)
        """The open keys, sorted."""
        self._row_of = np.zeros(0, np.int64)
        """The row of each key of ``_sorted``."""

    def _alloc(self, rows: int) -> None:
        self._key = np.zeros(rows, np.int64)
        self._cells = np.full((rows, self._s, FRAME_CELLS), MISSING, np.int64)
        self._last = np.zeros(rows, np.int64)
        self._shown = np.zeros(rows, bool)
        self._end = np.zeros(rows, np.int64)

    def _arrays(self) -> tuple[np.ndarray, ...]:
        return self._key, self._cells, self._last, self._shown, self._end

    # Views of the rows in use; writes through them change the table.
    @property
    def keys(self) -> np.ndarray:
        return self._key[:self.n]

    @property
    def cells(self) -> np.ndarray:
        return self._cells[:self.n]

    @property
    def last(self) -> np.ndarray:
        """Each frame's newest event time (node clock)."""
        return self._last[:self.n]

    @property
    def shown(self) -> np.ndarray:
        return self._shown[:self.n]

    @property
    def end(self) -> np.ndarray:
        """Where each shown frame's chain ended (0 for the others)."""
        return self._end[:self.n]

    @property
    def flat_cells(self) -> np.ndarray:
        """Every row's cells as one flat array: row r, stage s, point p at ``(r * stages + s) * FRAME_CELLS + p``."""
        return self._cells.reshape(-1)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self._arrays()) + self._sorted.nbytes + self._row_of.nbytes

    def locate(self, key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each key's row, and whether it is open (the row is meaningless where not)."""
        if len(self._sorted) == 0:
            return np.zeros(len(key), np.int64), np.zeros(len(key), bool)
        pos = np.minimum(np.searchsorted(self._sorted, key), len(self._sorted) - 1)
        return self._row_of[pos], self._sorted[pos] == key

    def open(self, new_keys: np.ndarray) -> None:
        """Open frames with these keys (unique, none open): rows appended, cells missing."""
        k = len(new_keys)
        if k == 0:
            return
        n = self.n
        if n + k > len(self._key):
            old = self._arrays()
            self._alloc(max(2 * len(self._key), n + k))
            for big, small in zip(self._arrays(), old):
                big[:n] = small[:n]
        self._key[n:n + k] = new_keys
        self._cells[n:n + k] = MISSING
        self._last[n:n + k] = 0
        self._shown[n:n + k] = False
        self._end[n:n + k] = 0
        self.n = n + k
        keys = np.concatenate([self._sorted, new_keys])
        order = np.argsort(keys, kind="stable")
        self._sorted = keys[order]
        self._row_of = np.concatenate([self._row_of, np.arange(n, n + k)])[order]

    def keep(self, rows: np.ndarray) -> None:
        """Keep the rows where ``rows`` (a mask over the open rows) is true, in their order; the others close."""
        idx = np.flatnonzero(rows)
        k = len(idx)
        if k == self.n:
            return
        if len(self._key) > 4 * max(k, MIN_ROWS):  # most frames left: give the memory back
            old = self._arrays()
            self._alloc(2 * max(k, MIN_ROWS))
            for big, small in zip(self._arrays(), old):
                big[:k] = small[idx]
        else:
            for a in self._arrays():
                a[:k] = a[idx]
        self.n = k
        order = np.argsort(self._key[:k], kind="stable")
        self._sorted = self._key[:k][order]
        self._row_of = order.astype(np.int64)
