"""Build and load the native library (the probes' ring and tracepoints, and the GStreamer tracer).

The library (its C modules in ``c/``, compiled by :mod:`dcuscope.core.cbuild`) is
``_build/libgstdcuscope.so`` beside this file. In a checkout it is compiled on demand (git-ignored;
the project setup runs ``python -m dcuscope.probes.capture.native build`` once). Installed, the
package's build compiled it, or wrote why not (``_build/BUILD-STATE``): nothing is compiled into
site-packages then. Where there is no library, :func:`load` returns None and says why in
:func:`unavailable_reason`, and the tracer falls back to Python probes (``probes.capture.ring``).

    python -m dcuscope.probes.capture.native build     # compile (again), print the path
    python -m dcuscope.probes.capture.native check     # load it and print the ABI, or why it cannot be loaded
"""

from __future__ import annotations

import ctypes
import sys
import threading
from pathlib import Path

import numpy as np

from dcuscope.core import cbuild
from dcuscope.core.errors import DcuscopeError
from dcuscope.core.gst import Gst
from dcuscope.probes.capture.ring import RingStats
from dcuscope.protocol.events import EVENT_DTYPE

HERE = Path(__file__).resolve().parent
C_DIR = HERE / "c"
BUILD_DIR = HERE / "_build"
LIBRARY = BUILD_DIR / cbuild.LIBRARY_NAME
ABI_VERSION = 2

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_reason: str | None = None


class BuildError(DcuscopeError):
    """The native library could not be compiled; the message says what was missing."""


def build(force: bool = False) -> Path:
    """Compile the library unless an up-to-date one is there; returns its path. Installed, only
    says whether the install built it."""
    try:
        return cbuild.ensure(C_DIR, LIBRARY, force=force)
    except cbuild.NotBuilt as exc:
        raise BuildError(f"dcuscope was installed without its native library ({exc.state}); "
                         f"install {cbuild.PACKAGES} (Debian/Ubuntu names) and reinstall dcuscope") from exc
    except cbuild.CBuildError as exc:
        raise BuildError(str(exc)) from exc


def _bind(lib: ctypes.CDLL) -> None:
    p, u64, i32 = ctypes.c_void_p, ctypes.c_uint64, ctypes.c_int
    sigs = {
        "dcu_abi_version": (i32, []),
        "dcu_event_size": (i32, []),
        "dcu_ring_new": (p, [u64]),
        "dcu_ring_free": (None, [p]),
        "dcu_ring_capacity": (u64, [p]),
        "dcu_drain": (u64, [p, p, u64]),
        "dcu_stats": (None, [p, ctypes.POINTER(u64), ctypes.POINTER(u64), ctypes.POINTER(u64)]),
        "dcu_attach": (ctypes.c_ulong, [p, p, i32, i32, i32]),
        "dcu_detach": (None, [p, ctypes.c_ulong]),
        "dcu_now": (ctypes.c_int64, [i32]),
        "dcu_push": (u64, [p, p, u64]),
        "dcu_hook_calls": (u64, []),
        "dcu_hook_attach": (ctypes.c_ulong, [p, p, i32, i32, i32]),
        "dcu_hook_detach": (None, [p]),
        "dcu_tracer_new": (p, [ctypes.c_char_p]),
        "dcu_tracer_finish": (None, [p]),
    }
    for name, (res, args) in sigs.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args


def load(build_if_missing: bool = True) -> ctypes.CDLL | None:
    """The loaded library, built first if needed; None (see :func:`unavailable_reason`) if not."""
    global _lib, _reason
    with _lock:
        if _lib is not None or _reason is not None:
            return _lib
        try:
            path = build() if build_if_missing else LIBRARY
            lib = ctypes.CDLL(str(path))  # CDLL: calls release the GIL
            _bind(lib)
            if lib.dcu_abi_version() != ABI_VERSION or lib.dcu_event_size() != EVENT_DTYPE.itemsize:
                raise BuildError(f"{path.name} is stale (ABI {lib.dcu_abi_version()}); rebuild it")
            _lib = lib
        except (BuildError, OSError, AttributeError) as exc:
            _reason = str(exc)
        return _lib


def unavailable_reason() -> str | None:
    """Why :func:`load` returned None, or None when the library is loaded or not yet tried."""
    return _reason


def hook_calls() -> int:
    """How many times the library's push-post hooks ran in this process (all pads)."""
    lib = load()
    return int(lib.dcu_hook_calls()) if lib is not None else 0


_capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_capsule_pointer.restype = ctypes.c_void_p
_capsule_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]


def gpointer(obj: Gst.Object) -> int:
    """The C address of a GObject wrapped by PyGObject (its ``__gpointer__`` capsule)."""
    return _capsule_pointer(obj.__gpointer__, None)


TRIGGERS = ("hooks", "probes")
"""What fires a native tracepoint: the dcuscope tracer's hooks (pad push/chain, the same tracer
``GST_TRACERS=dcuscope`` loads into any application) or a pad probe on the pad. The records
are the same (one C function writes both); see benchmarks/bench_probes.py for their costs."""
DEFAULT_TRIGGER = "hooks"


class NativeRing:
    """The C ring and its tracepoints; the same interface as :class:`dcuscope.probes.capture.ring.PythonRing`."""

    backend = "native"

    def __init__(self, capacity: int, lib: ctypes.CDLL | None = None, trigger: str = DEFAULT_TRIGGER):
        if trigger not in TRIGGERS:
            raise ValueError(f"unknown tracepoint trigger {trigger!r}; expected one of {', '.join(TRIGGERS)}")
        self.trigger = trigger
        self._ring = None
        self._lib = lib or load()
        if self._lib is None:
            raise BuildError(f"native probes unavailable: {unavailable_reason()}")
        self._ring = self._lib.dcu_ring_new(capacity)
        if not self._ring:
            raise MemoryError(f"cannot allocate a ring of {capacity} events")
        self.capacity = int(self._lib.dcu_ring_capacity(self._ring))
        self._drain_lock = threading.Lock()  # one consumer at a time; producers never take it

    def attach(self, pad: Gst.Pad, stage: int, point: int, clock_id: int) -> int:
        """Add a tracepoint on ``pad``; returns a handle for :meth:`detach`."""
        attach = self._lib.dcu_hook_attach if self.trigger == "hooks" else self._lib.dcu_attach
        handle = attach(self._ring, gpointer(pad), stage, point, clock_id)
        if not handle:
            raise ValueError(f"cannot add a tracepoint on {pad}")
        return int(handle)

    def detach(self, pad: Gst.Pad, handle: int) -> None:
        if self.trigger == "hooks":
            self._lib.dcu_hook_detach(gpointer(pad))
        else:
            self._lib.dcu_detach(gpointer(pad), handle)

    def drain(self, max_events: int | None = None) -> np.ndarray:
        """Events recorded since the last drain (oldest first), as EVENT_DTYPE."""
        limit = self.capacity if max_events is None else max_events
        out = np.empty(limit, EVENT_DTYPE)
        with self._drain_lock:
            n = self._lib.dcu_drain(self._ring, out.ctypes.data, limit)
        return out[:n].copy() if n < limit // 2 else out[:n]

    def push(self, events: np.ndarray) -> int:
        """Append events made elsewhere (drops, facts); returns how many went in (0 or all)."""
        events = np.ascontiguousarray(events, EVENT_DTYPE)
        return int(self._lib.dcu_push(self._ring, events.ctypes.data, len(events)))

    def stats(self) -> RingStats:
        w, d, u = ctypes.c_uint64(), ctypes.c_uint64(), ctypes.c_uint64()
        self._lib.dcu_stats(self._ring, ctypes.byref(w), ctypes.byref(d), ctypes.byref(u))
        return RingStats(written=w.value, dropped=d.value, unidentified=u.value)

    def now(self, clock_id: int) -> int:
        return int(self._lib.dcu_now(clock_id))

    def close(self) -> None:
        """Drop Python's reference; probes still attached keep the C ring alive."""
        if getattr(self, "_ring", None):
            self._lib.dcu_ring_free(self._ring)
            self._ring = None

    def __del__(self):
        self.close()


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    cmd = args[0] if args else "build"
    if cmd == "build":
        try:
            print(build(force=True))
        except BuildError as exc:
            print(f"dcuscope: native probes not built ({exc}); Python probes will be used", file=sys.stderr)
            return 1
        return 0
    if cmd == "check":
        lib = load()
        if lib is None:
            print(f"native probes unavailable: {unavailable_reason()}", file=sys.stderr)
            return 1
        print(f"{LIBRARY} ABI {lib.dcu_abi_version()}")
        return 0
    print("usage: python -m dcuscope.probes.capture.native [build|check]", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
