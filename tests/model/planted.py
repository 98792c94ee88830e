"""The compiled core's C with one mistake planted, for tests that show their comparison can fail."""

from __future__ import annotations

import shutil
from pathlib import Path

from dcuscope.model import compiled


def planted_sources(folder: Path, module: str, right: str, wrong: str) -> Path:
    """A copy of ``model/c`` in ``folder/c`` whose ``module`` (e.g. ``merge.c``) has ``right`` made ``wrong``."""
    shutil.copytree(compiled.C_DIR, folder / "c")
    source = (compiled.C_DIR / module).read_text()
    assert right in source, f"{module} no longer holds {right!r}"
    (folder / "c" / module).write_text(source.replace(right, wrong))
    return folder / "c"


def planted_core(folder: Path, module: str, right: str, wrong: str) -> compiled.CompiledCore:
    """:func:`planted_sources`, compiled and loaded."""
    import ctypes

    from dcuscope.core import cbuild

    library = cbuild.compile_library(planted_sources(folder, module, right, wrong), folder / "wrong.so", cbuild.CORE)
    return compiled.CompiledCore(ctypes.CDLL(str(library)))
