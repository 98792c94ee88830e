"""The compiled core: build and load ``c/`` (batch.c, merge.c, judge.c, push.c, stats.c; a C compiler is
all it needs).

What the relay's live path does per event, in one C library with a narrow interface: a wire batch
decoded and checked (:meth:`CompiledCore.decode_header`), its events paired into a run's open frames
(:attr:`CompiledCore.merge`, for :class:`dcuscope.relay.live.opentable.OpenTable`), frames judged by
the delay model (:meth:`CompiledCore.judge`, for :func:`dcuscope.model.delays.frame_delays`, which the
offline tools and the relay both call: one delay model; :attr:`CompiledCore.judge_rows`, a run's open
frames judged at a push tick with the columns it pushes of them), those columns moved to the relay's
clock for a push (:attr:`CompiledCore.push_columns`), and delay series gathered from frames' figures
(:meth:`CompiledCore.series`, for :func:`dcuscope.model.delays.series_of`) and summarized: count, mean and
percentiles (:meth:`CompiledCore.summarize` for :func:`dcuscope.model.delays.summaries`, which every
statistic goes through; :meth:`CompiledCore.summarize_held` for the relay's whole-run series,
:meth:`dcuscope.relay.live.values.RunValues.summaries`). The numpy code beside each stays the
reference, and what runs where this library cannot be had; tests hold the two to one another on real
traces (tests/model/test_compiled_judge.py, tests/model/test_compiled_stats.py,
tests/relay/live/test_live_merge.py, tests/relay/ingest/test_batch_check.py), and tests/model/fuzz
feeds it hostile input under AddressSanitizer and UndefinedBehaviorSanitizer.

The library is ``_build/libdcuscope_core.so`` beside this file: compiled on demand in a checkout
(git-ignored), by the package's build when installed (which writes ``_build/BUILD-STATE``: ``built``, or
why not). Where it cannot be had, whatever loads it says why once in its log (the relay's) and numpy
does the work, ~1 µs more per event at the relay (docs/benchmarks-log.md, issue 66).

    python -m dcuscope.model.compiled build     # compile (again), print the path
    python -m dcuscope.model.compiled check     # load it, or say why it cannot be loaded
    DCUSCOPE_COMPILED=0 dcuscope relay ...      # the numpy reference instead, as without a compiler
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import threading
from pathlib import Path

import numpy as np

from dcuscope.core import cbuild
from dcuscope.core.errors import DcuscopeError
from dcuscope.protocol.events import CODE_TABLE, EVENT_DTYPE
from dcuscope.protocol.wire import FRAME_LIMIT, MAX_BATCH_EVENTS, SOURCE_LIMIT

HERE = Path(__file__).resolve().parent
C_DIR = HERE / "c"
BUILD_DIR = HERE / "_build"
LIBRARY = BUILD_DIR / cbuild.CORE.name
ABI = 7
SUMMARY = 6
"""Figures of a summarized series: count, mean, p50, p95, p99, max (c/stats.c)."""
SERIES_KINDS = ("glass", "stages", "service", "wait", "gaps")
"""What a series :meth:`CompiledCore.series` gathers is, by the kind number of its row (c/core.h)."""
WORK_KEPT = 4 << 20
"""Bytes of work arrays a thread keeps between calls of the core at most (:meth:`CompiledCore._room`)."""
BATCH_OK, BATCH_INFLATE = 0, 1
""":meth:`CompiledCore.decode_header`'s answers besides a fault (negative): the events are checked, or
the payload is compressed (inflate it, then :meth:`CompiledCore.first_invalid`)."""

SWITCH = "DCUSCOPE_COMPILED"
"""``DCUSCOPE_COMPILED=0`` in a process's environment: it runs the numpy reference, as without a compiler."""

log = logging.getLogger(__name__)
_lock = threading.Lock()
_loaded: CompiledCore | None = None
_reason: str | None = None


class BuildError(DcuscopeError):
    """The core library could not be compiled; the message says why."""


class Judge(ctypes.Structure):
    """``judge_t`` of ``c/core.h``: where :meth:`CompiledCore.judge` reads a table and writes its figures."""

    _fields_ = [("n", ctypes.c_int64), ("s", ctypes.c_int32),
                *((name, ctypes.c_void_p) for name in ("origin", "origin_stage", "capture", "enter", "exit", "ready",
                                                        "has_exit", "links")),
                ("n_links", ctypes.c_int32),
                *((name, ctypes.c_void_p) for name in ("t_out", "prev", "end", "passed", "complete", "delay", "gap",
                                                        "service", "wait", "frame", "glass", "scratch"))]


def _signatures() -> dict[str, tuple]:
    """Each function of ``c/core.h`` the loader binds: (its result type, its argument types)."""
    p, i64, i32, c_int = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32, ctypes.c_int
    return {
        "dcu_merge_rehash": (None, [p, i64, p, p, i64]),
        "dcu_merge_locate": (None, [p, i64, p, p, i64, p, p]),
        "dcu_merge": (i64, [p, i64, i32, p, p, i64, p, p, p, p, p, i64, i64, p, p, i64, p, p]),
        "dcu_check": (i64, [p, i64, i32, p, i64, i64]),
        "dcu_unknown_source": (i64, [p, i64, i64, p, i64]),
        "dcu_decode_batch": (c_int, [ctypes.c_char_p, i64, i32, i64, p, i64, i64, p]),
        "dcu_judge": (c_int, [ctypes.POINTER(Judge)]),
        "dcu_judge_rows": (i64, [p, p, p, i64, i32, p, p, i32, p, p, p, p, p]),
        "dcu_origins": (i64, [p, i64, i64, p, p, p, p, p, i64, p]),
        "dcu_push_columns": (None, [p, p, i64, i32, p, p, p, p, p, p, i64, i64, p, p]),
        "dcu_summarize": (None, [p, p, i64, p]),
        "dcu_summarize_held": (None, [p, p, p, p, p, p, i64, p, p]),
        "dcu_series": (i64, [i64, i32, p, p, p, p, p, p, p, p, p, p, p, p, p]),
    }


class CompiledCore:
    """The library's functions, bound (see ``c/core.h`` for what each does)."""

    def __init__(self, dll: ctypes.CDLL) -> None:
        dll.dcu_core_abi.restype = ctypes.c_int
        dll.dcu_event_size.restype = ctypes.c_int
        if dll.dcu_core_abi() != ABI or dll.dcu_event_size() != EVENT_DTYPE.itemsize:
            raise BuildError(f"{LIBRARY.name} is of another version (ABI {dll.dcu_core_abi()}, this dcuscope needs {ABI})")
        for name, (restype, argtypes) in _signatures().items():
            fn = getattr(dll, name)
            fn.restype, fn.argtypes = restype, argtypes
        self.rehash = dll.dcu_merge_rehash
        self.locate = dll.dcu_merge_locate
        self.merge = dll.dcu_merge
        self._check = dll.dcu_check
        self._unknown = dll.dcu_unknown_source
        self._decode = dll.dcu_decode_batch
        self._judge = dll.dcu_judge
        self.judge_rows = dll.dcu_judge_rows
        """``dcu_judge_rows`` (c/judge.c): a run's open rows judged, with the columns a push carries of them."""
        self.origins = dll.dcu_origins
        """``dcu_origins`` (c/merge.c): a batch's origins counted per source and time bin (:class:`OriginCounter`)."""
        self.push_columns = dll.dcu_push_columns
        """``dcu_push_columns`` (c/push.c): those columns moved to the relay's clock, field after field."""
        self._summarize = dll.dcu_summarize
        self._summarize_held = dll.dcu_summarize_held
        self._series = dll.dcu_series
        self._work = threading.local()
        self._codes = np.ascontiguousarray(CODE_TABLE, np.uint8)
        self._codes_at = self._codes.ctypes.data
        self._head = np.zeros(4, np.int64)
        self._head_at = self._head.ctypes.data

    def first_invalid(self, events: np.ndarray, n_stages: int) -> int:
        """The index of the first event of ``events`` (EVENT_DTYPE, contiguous) that
        :func:`dcuscope.protocol.wire.check_events` refuses, or -1."""
        return self._check(events.ctypes.data, len(events), n_stages, self._codes_at, SOURCE_LIMIT, FRAME_LIMIT)

    def first_unknown(self, sources: np.ndarray, ids: np.ndarray) -> int:
        """The index of the first of ``sources`` (int32, one dimension, any stride: e.g. a batch's
        ``events["source"]``) not among ``ids`` (int64, sorted, contiguous), or -1."""
        return self._unknown(sources.ctypes.data, len(sources), sources.strides[0], ids.ctypes.data, len(ids))

    def decode_header(self, data: bytes, n_stages: int, max_events: int = MAX_BATCH_EVENTS) -> tuple[int, int, int]:
        """``data`` (a wire batch, bytes) read and, uncompressed, its events checked, in one pass:
        (:data:`BATCH_OK`, :data:`BATCH_INFLATE` or a fault, below 0; its sequence number; its event count)."""
        code = self._decode(data, len(data), n_stages, max_events, self._codes_at, SOURCE_LIMIT, FRAME_LIMIT,
                            self._head_at)
        return code, int(self._head[0]), int(self._head[1])

    def summarize(self, values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """``dcu_summarize``: series ``values[offsets[i]:offsets[i + 1]]`` (float64, contiguous, reordered
        in place; offsets int64) summarized, a row of :data:`SUMMARY` figures each (NaN: none)."""
        out = np.empty((len(offsets) - 1, SUMMARY))
        self._summarize(values.ctypes.data, offsets.ctypes.data, len(offsets) - 1, out.ctypes.data)
        return out

    def summarize_held(self, held: list[np.ndarray], n_sorted: list[int], n_held: list[int], held_ns: list[float],
                       extra: list[np.ndarray]) -> np.ndarray:
        """``dcu_summarize_held``: whole-run series, each ``held[i][:n_held[i]]`` (float64, contiguous;
        ascending up to ``n_sorted[i]``, the rest sorted in, in place; their whole ns summed ``held_ns[i]``)
        with ``extra[i]``, summarized as :meth:`summarize` summarizes their union, a row each."""
        k = len(held)
        at = np.array([h.ctypes.data for h in held], np.uint64)
        sorted_, n = np.array(n_sorted, np.int64), np.array(n_held, np.int64)
        offsets = np.zeros(k + 1, np.int64)
        np.cumsum([len(e) for e in extra], out=offsets[1:])
        values = np.concatenate(extra) if k else np.zeros(0)  # a copy: the core sorts it
        scratch = np.empty(max(1, int((n - sorted_).max(initial=0))))
        out = np.empty((k, SUMMARY))
        self._summarize_held(at.ctypes.data, sorted_.ctypes.data, n.ctypes.data,
                             np.array(held_ns, np.float64).ctypes.data, values.ctypes.data, offsets.ctypes.data, k,
                             scratch.ctypes.data, out.ctypes.data)
        return out

    def series(self, per_stage: list[np.ndarray], glass: np.ndarray, prev: np.ndarray, first: np.ndarray,
               has_exit: np.ndarray) -> tuple[list[tuple[str, int, int, np.ndarray]], np.ndarray]:
        """``dcu_series``: the delay series of frames' values (``per_stage``: the four (n, s) columns of
        :data:`dcuscope.model.delays.STAGE_COLUMNS`; ``glass``, ``prev``, ``first`` as
        :class:`~dcuscope.model.delays.FrameValues` holds them): (kind (:data:`SERIES_KINDS`), a, b, values)
        of each series in order, and each stage's busy time (NaN without service times)."""
        n, s = prev.shape
        cols = [np.ascontiguousarray(c, np.float64) for c in per_stage]
        glass = np.ascontiguousarray(glass, np.float64)
        prev, first = np.ascontiguousarray(prev, np.int64), np.ascontiguousarray(first, np.uint8)
        has_exit = np.ascontiguousarray(has_exit, np.uint8)
        out, scratch = self._room("out", n * (4 * s + 1), np.float64), self._room("scratch", max(1, n), np.float64)
        rows, pairs = np.empty((1 + 3 * s + s * s, 4), np.int64), np.empty(max(1, s * s), np.int64)
        busy = np.empty(s)
        k = self._series(n, s, *(c.ctypes.data for c in cols), glass.ctypes.data, prev.ctypes.data, first.ctypes.data,
                         has_exit.ctypes.data, out.ctypes.data, rows.ctypes.data, busy.ctypes.data, pairs.ctypes.data,
                         scratch.ctypes.data)
        made, at = [], 0
        for kind, a, b, count in rows[:k].tolist():
            made.append((SERIES_KINDS[kind], a, b, out[at:at + count].copy()))  # arrays of their own, as numpy's
            at += count
        return made, busy

    def _room(self, name: str, size: int, dtype) -> np.ndarray:
        """A work array of this thread's, at least ``size`` long, kept from call to call up to
        :data:`WORK_KEPT` bytes: one of a fresh ~300 kB a call (a rolling window's series) made the
        allocator hand its pages back and fault them in again, which cost more than numpy's calls."""
        kept = getattr(self._work, name, None)
        if kept is not None and len(kept) >= size:
            return kept
        made = np.empty(size, dtype)
        if made.nbytes <= WORK_KEPT:
            setattr(self._work, name, made)
        return made

    def judge(self, j: Judge) -> int:
        """``dcu_judge``: the figures of ``j``'s frames written where it says; returns how many are complete."""
        return self._judge(ctypes.byref(j))


class OriginCounter:
    """A run's batches' origins counted per (source, time bin) in one compiled pass, into buffers kept
    from batch to batch (their addresses taken once per size)."""

    def __init__(self, core: CompiledCore, bin_ns: int) -> None:
        self._core, self._bin_ns, self._room = core, bin_ns, 0

    def count(self, events: np.ndarray) -> tuple[list[list[int]], int]:
        """Of ``events`` (EVENT_DTYPE, contiguous, checked): ([sources, bins, counts], each a list of the
        distinct (source, bin) pairs in the order they first come), and the greatest point of the batch."""
        n = len(events)
        if n > self._room:
            self._room = 1 << max(8, (n - 1).bit_length())
            self._out, self._top = np.empty((3, self._room), np.int64), np.zeros(1, np.int64)
            self._hkey, self._hrow = np.empty(2 * self._room, np.int64), np.empty(2 * self._room, np.int64)
            self._at = (*(row.ctypes.data for row in self._out), self._hkey.ctypes.data, self._hrow.ctypes.data,
                        2 * self._room - 1, self._top.ctypes.data)
        m = self._core.origins(events.ctypes.data, n, self._bin_ns, *self._at)
        return self._out[:, :m].tolist(), int(self._top[0])


def links_of(links: list, stages: int) -> np.ndarray:
    """A trace header's links as the compiled judge takes them, (n, 2) int32: those the graph cannot have
    left out, as :func:`dcuscope.model.delays.chains` leaves them; a graph of none of them stays a graph
    (one pair the judge skips), as it does there; no links, one chain (none)."""
    if not links:
        return np.zeros((0, 2), np.int32)
    valid = [(a, b) for a, b in links if 0 <= a < stages and 0 <= b < stages and a != b]
    return np.array(valid or [(-1, -1)], np.int32)


def build(force: bool = False) -> Path:
    """Compile the library unless an up-to-date one is there; returns its path. Installed, only
    says whether the install built it."""
    try:
        return cbuild.ensure(C_DIR, LIBRARY, cbuild.CORE, force)
    except cbuild.NotBuilt as exc:
        raise BuildError(f"dcuscope was installed without its compiled core ({exc.state}); install gcc and "
                         f"reinstall") from exc
    except cbuild.CBuildError as exc:
        raise BuildError(str(exc)) from exc


def load() -> CompiledCore | None:
    """The compiled core (built first where needed), or None; the reason is logged once and kept
    (:func:`unavailable_reason`)."""
    global _loaded, _reason
    with _lock:
        if _loaded is None and _reason is None:
            try:
                if os.environ.get(SWITCH) == "0":
                    raise BuildError(f"switched off ({SWITCH}=0)")
                _loaded = CompiledCore(ctypes.CDLL(str(build())))
            except (BuildError, OSError) as exc:
                _reason = str(exc).splitlines()[0]
                log.warning("compiled core unavailable (%s): batches are decoded, paired and judged with numpy, "
                            "~1 µs more per event", _reason)
        return _loaded


def unavailable_reason() -> str | None:
    """Why :func:`load` gave None (None when it loaded, or was not tried)."""
    return _reason


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args == ["build"]:
        try:
            print(build(force=True))
        except BuildError as exc:
            print(f"dcuscope: compiled core not built ({exc}); numpy will do its work", file=sys.stderr)
            return 1
        return 0
    if args == ["check"]:
        if load() is None:
            print(f"compiled core unavailable: {unavailable_reason()}", file=sys.stderr)
            return 1
        print(f"compiled core loaded: {LIBRARY}")
        return 0
    print("usage: python -m dcuscope.model.compiled build|check", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
