"""Compile the probes' native library (``probes/capture/c``) with the system's compiler and GStreamer,
and the compiled core of the delay model and the relay's live path (``model/c``, :data:`CORE`), which
needs a C compiler only.

Standard library only: ``setup.py`` loads this file by its path while a wheel is built (nothing of
dcuscope nor numpy is importable then), and :mod:`dcuscope.probes.capture.native` and
:mod:`dcuscope.model.compiled` call it in a checkout. Where the build puts a library it also
writes :data:`STATE`: one line, ``built`` or why not; an installed dcuscope reads it instead of
compiling (site-packages is not ours to write).
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import tempfile
from pathlib import Path

MODULES = ("frames", "ring", "graph", "links", "deepstream", "writer", "tracer", "padprobe", "plugin")
"""The C modules, bottom-up: each calls only those before it, through their headers
(docs/development.md, "Layout"; ``tests/test_layers.py`` checks it)."""
LIBRARY_NAME = "libgstdcuscope.so"
STATE = "BUILD-STATE"
"""Beside the library in an installed dcuscope: ``built``, or why the install built nothing."""
PACKAGES = "gcc pkg-config libgstreamer1.0-dev"
"""What the build needs, as Debian and Ubuntu name it."""


class Library:
    """A shared library: its C modules (bottom-up), its file name, whether it links GStreamer."""

    def __init__(self, modules: tuple[str, ...], name: str, gstreamer: bool) -> None:
        self.modules, self.name, self.gstreamer = modules, name, gstreamer


PROBES = Library(MODULES, LIBRARY_NAME, gstreamer=True)
CORE = Library(("batch", "merge", "judge", "push", "stats"), "libdcuscope_core.so", gstreamer=False)
"""The compiled core (model/c): batches decoded and checked, paired into frames, judged by the delay
model, their series summarized. No GStreamer, so a relay-only host builds it too."""


class CBuildError(Exception):
    """The library could not be compiled; the message says what was missing."""


class NotBuilt(CBuildError):
    """An installed dcuscope whose package build compiled no such library: ``state`` says why."""

    def __init__(self, state: str) -> None:
        super().__init__(state)
        self.state = state


def sources(c_dir: Path, library: Library = PROBES) -> list[Path]:
    return [c_dir / f"{name}.c" for name in library.modules]


def _compiler() -> str:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        raise CBuildError("no C compiler (cc/gcc) on PATH")
    return cc


def _gst_flags() -> list[str]:
    if not shutil.which("pkg-config"):
        raise CBuildError("pkg-config not found")
    res = subprocess.run(["pkg-config", "--cflags", "--libs", "gstreamer-1.0"], capture_output=True, text=True)
    if res.returncode != 0:
        raise CBuildError(f"GStreamer development files not found: {res.stderr.strip()}")
    return shlex.split(res.stdout)


def compile_library(c_dir: Path, library: Path, which: Library = PROBES) -> Path:
    """Compile the C modules of ``c_dir`` (those of ``which``) into ``library``; raises :class:`CBuildError`."""
    library.parent.mkdir(parents=True, exist_ok=True)
    # Compile to a private name and rename: two processes building at once never load a
    # half-written library (nor GStreamer's plugin scanner, which looks at every *.so there).
    fd, tmp = tempfile.mkstemp(suffix=".tmp", dir=library.parent)
    os.close(fd)
    # -ffp-contract=off: no multiply-add fused where the source has two roundings (aarch64 has the
    # instruction): the compiled core's figures stay numpy's to the last bit there too.
    cmd = [_compiler(), "-O2", "-std=gnu11", "-ffp-contract=off", "-Wall", "-Werror=implicit-function-declaration",
           "-shared", "-fPIC", "-o", tmp, *map(str, sources(c_dir, which)), *(_gst_flags() if which.gstreamer else []), "-lm"]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as exc:
        os.unlink(tmp)
        raise CBuildError(f"cannot run the C compiler {cmd[0]}: {exc.strerror}") from exc
    if res.returncode != 0:
        os.unlink(tmp)
        raise CBuildError(f"compiling {which.name} failed:\n{res.stderr.strip()}")
    os.replace(tmp, library)
    return library


def installed_state(folder: Path) -> str | None:
    """``built``, or why the install built no library into ``folder``; None in a checkout (compiled on demand)."""
    try:
        return (folder / STATE).read_text().strip() or "unknown"
    except FileNotFoundError:
        return None


def ensure(c_dir: Path, library: Path, which: Library = PROBES, force: bool = False) -> Path:
    """``library``, compiled from ``c_dir`` unless one newer than its sources and headers is there.
    Installed (:data:`STATE` beside it), nothing is compiled: raises :class:`NotBuilt` when the
    install built none; :class:`CBuildError` when compiling fails."""
    state = installed_state(library.parent)
    if state is not None:
        if state == "built" and library.exists():
            return library
        raise NotBuilt(state)
    newest = max(p.stat().st_mtime for p in [*sources(c_dir, which), *c_dir.glob("*.h")])
    if not force and library.exists() and library.stat().st_mtime >= newest:
        return library
    return compile_library(c_dir, library, which)


def build_for_install(c_dir: Path, folder: Path, which: Library = PROBES) -> str | None:
    """Compile into ``folder`` as a package build does: writes :data:`STATE`; returns why it
    built nothing (the package then uses Python probes and has no tracer, or the relay and the
    offline tools run the numpy reference of the core), or None."""
    (folder / which.name).unlink(missing_ok=True)  # an earlier build's, in a build folder used again
    try:
        compile_library(c_dir, folder / which.name, which)
    except CBuildError as exc:
        reason = str(exc).splitlines()[0]
        (folder / STATE).write_text(reason + "\n")
        return reason
    (folder / STATE).write_text("built\n")
    return None


if __name__ == "__main__":
    # Standard library only, Python 3.7+: a root filesystem without dcuscope builds with it
    # (scripts/platforms.sh): python3 core/cbuild.py probes/capture/c OUT/libgstdcuscope.so
    import sys

    try:
        print(compile_library(Path(sys.argv[1]), Path(sys.argv[2])))
    except (CBuildError, IndexError) as exc:
        sys.exit(f"cbuild: {exc or 'usage: cbuild.py C_DIR LIBRARY'}")
