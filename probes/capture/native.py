"""Build and load the native library (the probes' ring and tracepoints, and the GStreamer tracer).

The library (its C modules in ``c/``, in the order of :data:`MODULES`) is compiled on demand into
``probes/capture/_build/libgstdcuscope.so`` (git-ignored); the
project setup runs ``python -m probes.capture.native build`` once. Where there is no compiler or no
GStreamer headers, :func:`load` returns None and says why in :func:`unavailable_reason`, and
the tracer falls back to Python probes (``probes.capture.ring``).

    python -m probes.capture.native build     # compile (again), print the path
    python -m probes.capture.native check     # load it and print the ABI, or why it cannot be loaded
"""

from __future__ import annotations

import ctypes
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

from core.errors import DcuscopeError
from core.gst import Gst
from probes.capture.ring import RingStats
from probes.trace.events import EVENT_DTYPE

HERE = Path(__file__).resolve().parent
C_DIR = HERE / "c"
MODULES = ("frames", "ring", "graph", "deepstream", "writer", "tracer", "padprobe", "plugin")
"""The C modules, bottom-up: each calls only those before it, through their headers
(docs/development.md, "Layout"; ``tests/test_layers.py`` checks it)."""
SOURCES = [C_DIR / f"{name}.c" for name in MODULES]
HEADERS = sorted(C_DIR.glob("*.h"))
BUILD_DIR = HERE / "_build"
LIBRARY = BUILD_DIR / "libgstdcuscope.so"
ABI_VERSION = 2

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_reason: str | None = None


class BuildError(DcuscopeError):
    """The native library could not be compiled; the message says what was missing."""


def _compiler() -> str:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        raise BuildError("no C compiler (cc/gcc) on PATH")
    return cc


def _gst_flags() -> list[str]:
    if not shutil.which("pkg-config"):
        raise BuildError("pkg-config not found")
    res = subprocess.run(["pkg-config", "--cflags", "--libs", "gstreamer-1.0"], capture_output=True, text=True)
    if res.returncode != 0:
        raise BuildError(f"GStreamer development files not found: {res.stderr.strip()}")
    return shlex.split(res.stdout)


def build(force: bool = False) -> Path:
    """Compile the library unless an up-to-date one is there; returns its path."""
    newest = max(p.stat().st_mtime for p in SOURCES + HEADERS)
    if not force and LIBRARY.exists() and LIBRARY.stat().st_mtime >= newest:
        return LIBRARY
    BUILD_DIR.mkdir(exist_ok=True)
    # Compile to a private name and rename: two processes building at once never load a
    # half-written library (nor GStreamer's plugin scanner, which looks at every *.so there).
    fd, tmp = tempfile.mkstemp(suffix=".tmp", dir=BUILD_DIR)
    os.close(fd)
    cmd = [_compiler(), "-O2", "-std=gnu11", "-Wall", "-Werror=implicit-function-declaration", "-shared", "-fPIC", "-o", tmp, *map(str, SOURCES), *_gst_flags()]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as exc:
        os.unlink(tmp)
        raise BuildError(f"cannot run the C compiler {cmd[0]}: {exc.strerror}") from exc
    if res.returncode != 0:
        os.unlink(tmp)
        raise BuildError(f"compiling the native probes failed:\n{res.stderr.strip()}")
    os.replace(tmp, LIBRARY)
    return LIBRARY


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
    """The C ring and its tracepoints; the same interface as :class:`probes.capture.ring.PythonRing`."""

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
    print("usage: python -m probes.capture.native [build|check]", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
