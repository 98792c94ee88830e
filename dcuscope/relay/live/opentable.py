"""The open frames of a live run: rows in the order the frames opened, found by key through an index.

A paced node opens a few frames per batch while hundreds wait to settle. Kept sorted by key, the
table was copied whole and sorted again on every batch that opened one; here opening appends rows
(amortised, as :class:`dcuscope.relay.live.run.Grow`) and only :meth:`OpenTable.keep`
(finalisation and eviction, a few times a second) moves rows.

The index is a hash of the keys that the compiled merge (:mod:`dcuscope.model.compiled`) reads and
fills as it opens frames (:meth:`OpenTable.merge`); without that library, a sorted array of the keys,
sorted again when frames open.

Rows are in opening order, not key order: what reads the table takes frames as a set.
"""

from __future__ import annotations

import numpy as np

from dcuscope.model.frametable import MISSING
from dcuscope.protocol.events import EVENT_DTYPE, FRAME_CELLS
from dcuscope.relay.live import framepack
from dcuscope.model.compiled import CompiledCore

MIN_ROWS = 64
MIN_SLOTS = 256
"""Hash slots at least (a power of two, at least twice the rows open)."""


class OpenTable:
    """Open frames of one run: per row its key (``source << KEY_SHIFT | frame``), cells (the earliest
    timestamp of each (stage, point)), newest event time, whether it was shown, and where its chain ended."""

    def __init__(self, stages: int, compiled: CompiledCore | None = None) -> None:
        self._s = stages
        self.n = 0
        self._c = compiled
        self._alloc(MIN_ROWS)
        self._sorted = np.zeros(0, np.int64)
        """Without the compiled merge: the open keys, sorted."""
        self._row_of = np.zeros(0, np.int64)
        """The row of each key of ``_sorted``."""
        slots = MIN_SLOTS if compiled is not None else 0
        self._hkey = np.full(slots, -1, np.int64)
        """With the compiled merge: the hash's slots (key, -1 free) and each one's row."""
        self._hrow = np.zeros(slots, np.int64)
        self._io = np.zeros(4, np.int64)
        self._at: tuple[int, ...] | None = None
        """:meth:`_addresses` (None: taken again at the next merge)."""
        self._judge_room = 0
        """Frames :meth:`judge`'s buffers hold (grown as needed)."""

    @property
    def compiled(self) -> bool:
        """Whether the compiled merge keeps this table (:meth:`merge` may be called)."""
        return self._c is not None

    def _alloc(self, rows: int) -> None:
        self._key = np.zeros(rows, np.int64)
        self._cells = np.full((rows, self._s, FRAME_CELLS), MISSING, np.int64)
        self._last = np.zeros(rows, np.int64)
        self._shown = np.zeros(rows, bool)
        self._end = np.zeros(rows, np.int64)
        self._at = None

    def _addresses(self) -> tuple[int, ...]:
        """Where the compiled pass finds the hash and the rows: taken once per allocation, not per batch."""
        if self._at is None:
            self._at = tuple(a.ctypes.data for a in (self._hkey, self._hrow, *self._arrays(), self._io))
        return self._at

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
        index = self._sorted.nbytes + self._row_of.nbytes + self._hkey.nbytes + self._hrow.nbytes
        return sum(a.nbytes for a in self._arrays()) + index

    def locate(self, key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each key's row, and whether it is open (the row is meaningless where not)."""
        if self._c is not None:
            key = np.ascontiguousarray(key, np.int64)
            rows, found = np.empty(len(key), np.int64), np.empty(len(key), bool)
            self._c.locate(key.ctypes.data, len(key), self._hkey.ctypes.data, self._hrow.ctypes.data, len(self._hkey) - 1,
                           rows.ctypes.data, found.ctypes.data)
            return rows, found
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
        self._room(k)
        self._key[n:n + k] = new_keys
        self._cells[n:n + k] = MISSING
        self._last[n:n + k] = 0
        self._shown[n:n + k] = False
        self._end[n:n + k] = 0
        self.n = n + k
        if self._c is not None:
            self._reindex()
            return
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
        if self._c is not None:
            self._reindex()
            return
        order = np.argsort(self._key[:k], kind="stable")
        self._sorted = self._key[:k][order]
        self._row_of = order.astype(np.int64)

    def merge(self, events: np.ndarray, src_ids: np.ndarray, watermark: np.ndarray, has_exit: np.ndarray,
              newest: int) -> tuple[int, int, int]:
        """Merge a batch of events (EVENT_DTYPE) with the compiled pass: frames open as their first event
        comes (in event order), unless late (at or below their source's ``watermark``, ``src_ids`` sorted,
        every source of the batch among them); ``has_exit`` (bool per stage) is marked in place. Rows
        and hash slots grow as frames open (doubling); the caller keeps the table within its cap.
        Returns (late events, the newest frame event's time or ``newest``, frame events merged into a row)."""
        events = np.ascontiguousarray(events, dtype=EVENT_DTYPE)  # the records the C pass reads, kept alive here
        address = events.ctypes.data
        io = self._io
        io[:] = (0, newest, 0, 0)
        while True:
            hkey, hrow, key, cells, last, shown, end, io_at = self._addresses()
            n = self._c.merge(address, len(events), self._s, hkey, hrow, len(self._hkey) - 1, key, cells, last, shown, end,
                              self.n, len(self._key), src_ids.ctypes.data, watermark.ctypes.data, len(src_ids),
                              has_exit.ctypes.data, io_at)
            self.n = int(n)
            if io[3] == len(events):
                return int(io[0]), int(io[1]), int(io[2])
            # Out of rows or hash slots at event io[3], the frames before it merged: room, then on from there.
            self._room(max(self.n, MIN_ROWS))

    def judge(self, rows: np.ndarray, has_exit: np.ndarray, links: np.ndarray) -> tuple[np.ndarray, ...]:
        """The open ``rows`` judged by the compiled delay model (``has_exit``: bool per stage, the run's;
        ``links``: :func:`dcuscope.model.compiled.links_of`): (complete, end, ints, floats), the last two
        the columns a push carries of them (:func:`dcuscope.relay.live.framepack.node_columns`, the cursor
        row 0). Views of buffers this table keeps: valid until the next call."""
        k, s = len(rows), self._s
        ir, fr = framepack.int_rows(s), framepack.float_rows(s)
        if k > self._judge_room:
            self._judge_room = room = max(64, 2 * k)
            self._j = {"rows": np.empty(room, np.int64), "complete": np.empty(room, bool), "end": np.empty(room, np.int64),
                       "ints": np.empty(ir * room, np.int64), "floats": np.empty(fr * room), "work": np.empty(10 * s + 8, np.int64)}
            self._j_at = {name: a.ctypes.data for name, a in self._j.items()}
        j, at = self._j, self._j_at
        j["rows"][:k] = rows
        _, _, key, cells, *_ = self._addresses()
        self._c.judge_rows(cells, key, at["rows"], k, s, has_exit.ctypes.data, links.ctypes.data, len(links), at["complete"],
                           at["end"], at["ints"], at["floats"], at["work"])
        return j["complete"][:k], j["end"][:k], j["ints"][:ir * k].reshape(ir, k), j["floats"][:fr * k].reshape(fr, k)

    def _room(self, k: int) -> None:
        """Rows (and, compiled, hash slots) for ``k`` more frames."""
        n = self.n
        if n + k > len(self._key):
            old = self._arrays()
            self._alloc(max(2 * len(self._key), n + k))
            for big, small in zip(self._arrays(), old):
                big[:n] = small[:n]
        if self._c is not None and len(self._hkey) < 2 * (n + k):
            self._reindex(2 * (n + k))

    def _reindex(self, at_least: int = 0) -> None:
        """The hash of the open keys made again, with slots for ``at_least`` keys' worth (and never more
        than 8 times the rows open, so a table that emptied gives its memory back)."""
        want = max(MIN_SLOTS, 1 << int(max(2 * self.n, at_least) - 1).bit_length())
        if want > len(self._hkey) or len(self._hkey) > 4 * want:
            self._hkey, self._hrow = np.empty(want, np.int64), np.empty(want, np.int64)
            self._at = None
        self._c.rehash(self._key.ctypes.data, self.n, self._hkey.ctypes.data, self._hrow.ctypes.data, len(self._hkey) - 1)
