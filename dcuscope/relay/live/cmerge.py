"""The live engine's compiled merge: build and load ``c/merge.c`` (a C compiler is all it needs).

``relay.live.run.LiveRun`` merges each batch of events into its open frames in one compiled pass
when this library loads, and with numpy otherwise; both leave a run exactly alike
(tests/relay/live/test_live_merge.py). The library is ``_build/libdcuscope_merge.so`` beside this file:
compiled on demand in a checkout (git-ignored), by the package's build when installed (which writes
``_build/BUILD-STATE``: ``built``, or why not). Where it cannot be had the relay says why once in its
log and merges with numpy, which costs ~0.5 µs more per event (docs/benchmarks-log.md, issue 50, first step).

    python -m dcuscope.relay.live.cmerge build     # compile (again), print the path
    python -m dcuscope.relay.live.cmerge check     # load it, or say why it cannot be loaded
"""

from __future__ import annotations

import ctypes
import logging
import sys
import threading
from pathlib import Path

import numpy as np

from dcuscope.core import cbuild
from dcuscope.core.errors import DcuscopeError
from dcuscope.protocol.events import CODE_TABLE, EVENT_DTYPE
from dcuscope.protocol.wire import FRAME_LIMIT, SOURCE_LIMIT

HERE = Path(__file__).resolve().parent
C_DIR = HERE / "c"
BUILD_DIR = HERE / "_build"
LIBRARY = BUILD_DIR / cbuild.MERGE.name
ABI = 3

log = logging.getLogger(__name__)
_lock = threading.Lock()
_loaded: CompiledMerge | None = None
_reason: str | None = None


class BuildError(DcuscopeError):
    """The merge library could not be compiled; the message says why."""


class CompiledMerge:
    """The library's functions, bound (see ``c/merge.c`` for what each does)."""

    def __init__(self, dll: ctypes.CDLL) -> None:
        p, i64 = ctypes.c_void_p, ctypes.c_int64
        dll.dcu_merge_abi.restype = ctypes.c_int
        dll.dcu_merge_event_size.restype = ctypes.c_int
        if dll.dcu_merge_abi() != ABI or dll.dcu_merge_event_size() != EVENT_DTYPE.itemsize:
            raise BuildError(f"{LIBRARY.name} is of another version (ABI {dll.dcu_merge_abi()}, this dcuscope needs {ABI})")
        dll.dcu_merge_rehash.restype = None
        dll.dcu_merge_rehash.argtypes = [p, i64, p, p, i64]
        dll.dcu_merge_locate.restype = None
        dll.dcu_merge_locate.argtypes = [p, i64, p, p, i64, p, p]
        dll.dcu_merge.restype = i64
        dll.dcu_merge.argtypes = [p, i64, ctypes.c_int32, p, p, i64, p, p, p, p, p, i64, i64, p, p, i64, p, p]
        dll.dcu_check.restype = i64
        dll.dcu_check.argtypes = [p, i64, ctypes.c_int32, p, i64, i64]
        dll.dcu_unknown_source.restype = i64
        dll.dcu_unknown_source.argtypes = [p, i64, i64, p, i64]
        self.rehash = dll.dcu_merge_rehash
        self.locate = dll.dcu_merge_locate
        self.merge = dll.dcu_merge
        self._check = dll.dcu_check
        self._unknown = dll.dcu_unknown_source
        self._codes = np.ascontiguousarray(CODE_TABLE, np.uint8)
        self._codes_at = self._codes.ctypes.data

    def first_invalid(self, events: np.ndarray, n_stages: int) -> int:
        """The index of the first event of ``events`` (EVENT_DTYPE, contiguous) that
        :func:`dcuscope.protocol.wire.check_events` refuses, or -1."""
        return self._check(events.ctypes.data, len(events), n_stages, self._codes_at, SOURCE_LIMIT, FRAME_LIMIT)

    def first_unknown(self, sources: np.ndarray, ids: np.ndarray) -> int:
        """The index of the first of ``sources`` (int32, one dimension, any stride: e.g. a batch's
        ``events["source"]``) not among ``ids`` (int64, sorted, contiguous), or -1."""
        return self._unknown(sources.ctypes.data, len(sources), sources.strides[0], ids.ctypes.data, len(ids))


def build(force: bool = False) -> Path:
    """Compile the library unless an up-to-date one is there; returns its path. Installed, only
    says whether the install built it."""
    try:
        return cbuild.ensure(C_DIR, LIBRARY, cbuild.MERGE, force)
    except cbuild.NotBuilt as exc:
        raise BuildError(f"dcuscope was installed without its compiled merge ({exc.state}); install gcc and "
                         f"reinstall") from exc
    except cbuild.CBuildError as exc:
        raise BuildError(str(exc)) from exc


def load() -> CompiledMerge | None:
    """The compiled merge (built first where needed), or None; the reason is logged once and kept
    (:func:`unavailable_reason`)."""
    global _loaded, _reason
    with _lock:
        if _loaded is None and _reason is None:
            try:
                _loaded = CompiledMerge(ctypes.CDLL(str(build())))
            except (BuildError, OSError) as exc:
                _reason = str(exc).splitlines()[0]
                log.warning("live merge: numpy (the compiled merge is unavailable: %s)", _reason)
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
            print(f"dcuscope: compiled merge not built ({exc}); relays will merge with numpy", file=sys.stderr)
            return 1
        return 0
    if args == ["check"]:
        if load() is None:
            print(f"compiled merge unavailable: {unavailable_reason()}", file=sys.stderr)
            return 1
        print(f"compiled merge loaded: {LIBRARY}")
        return 0
    print("usage: python -m dcuscope.relay.live.cmerge build|check", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
