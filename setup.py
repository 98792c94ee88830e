"""How the repository becomes the one package ``dcuscope`` (pyproject.toml holds the metadata).

- The package is the folder ``dcuscope/`` as it stands (the repository's top-level ``core/`` …
  ``ui/`` are links into it); ``assets/`` (the models and clips, with their notes) and ``configs/``
  go in as ``dcuscope/assets`` and ``dcuscope/configs``.
- The native library (the GStreamer tracer and the tracepoints, ``probes/capture/c``) is compiled
  against the system's GStreamer as the package is built: :mod:`core.cbuild`, loaded here
  by its path. Without a compiler or GStreamer's headers the package is built all the same, says
  so in one line, and its Python probes are used (``dcuscope`` says so again where it matters).
- The wheel is tagged for the platform (it holds a shared library) but any Python 3.
"""

import importlib.util
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.bdist_wheel import bdist_wheel
from setuptools.command.build_py import build_py
from setuptools.dist import Distribution

ROOT = Path(__file__).resolve().parent
DATA = ("assets", "configs")
SKIP = {"__pycache__", "_build", "node_modules"}
"""Folders left out: bytecode, a checkout's own native build, npm's download (what the page loads is
copied to ui/static/vendor)."""


def _folders(top: Path, name: str) -> dict[str, str]:
    """``name.X.Y`` -> its folder, for ``top`` and every folder in it (a folder of data too:
    setuptools treats every folder as a package, and copies a package's files)."""
    out = {}
    for folder in [top, *sorted(p for p in top.rglob("*") if p.is_dir())]:
        rel = folder.relative_to(top)
        if any(part in SKIP or part.startswith(".") for part in rel.parts):
            continue
        out[".".join((name, *rel.parts))] = folder.relative_to(ROOT).as_posix()
    return out


PACKAGE_DIR = _folders(ROOT / "dcuscope", "dcuscope")
for _top in DATA:
    PACKAGE_DIR.update(_folders(ROOT / _top, f"dcuscope.{_top}"))
PACKAGE_DATA = {name: ["*"] for name, folder in PACKAGE_DIR.items() if not (ROOT / folder / "__init__.py").is_file()}
"""Every file of a data folder (ui/static, the C sources, the loader's entries, models, configs)."""


def _cbuild():
    spec = importlib.util.spec_from_file_location("dcuscope_cbuild", ROOT / "dcuscope" / "core" / "cbuild.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class BuildWithNative(build_py):
    """build_py, then the native library beside the package's copy of probes/capture and the compiled
    core beside model (not for an editable install: a checkout compiles them on demand,
    ``python -m dcuscope.probes.capture.native build``, ``python -m dcuscope.model.compiled build``)."""

    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return
        cbuild = _cbuild()
        folder = Path(self.build_lib) / "dcuscope" / "probes" / "capture" / "_build"
        folder.mkdir(parents=True, exist_ok=True)
        reason = cbuild.build_for_install(ROOT / "dcuscope" / "probes" / "capture" / "c", folder)
        if reason:
            print(f"dcuscope: native probes not built ({reason}): Python probes will be used and there is no "
                  f"GStreamer tracer; install {cbuild.PACKAGES} (Debian/Ubuntu) and reinstall", file=sys.stderr)
        folder = Path(self.build_lib) / "dcuscope" / "model" / "_build"
        folder.mkdir(parents=True, exist_ok=True)
        reason = cbuild.build_for_install(ROOT / "dcuscope" / "model" / "c", folder, cbuild.CORE)
        if reason:
            print(f"dcuscope: the compiled core not built ({reason}): relays and offline tools will run its numpy "
                  f"reference; install gcc and reinstall", file=sys.stderr)
        if not (ROOT / "dcuscope" / "ui" / "static" / "vendor").is_dir():
            print("dcuscope: ui/static/vendor is missing (make setup, or python -m dcuscope.ui.vendor --npm): "
                  "the page will poll the HTTP API instead of Socket.IO", file=sys.stderr)


class PlatformWheel(bdist_wheel):
    """The library is not a Python extension: one wheel per platform serves every Python 3."""

    def get_tag(self):
        _, _, platform = super().get_tag()
        return "py3", "none", platform


class NativeDistribution(Distribution):
    def has_ext_modules(self):
        return True  # platlib, and a platform tag


setup(
    package_dir=PACKAGE_DIR,
    packages=sorted(PACKAGE_DIR),
    package_data=PACKAGE_DATA,
    cmdclass={"build_py": BuildWithNative, "bdist_wheel": PlatformWheel},
    distclass=NativeDistribution,
)
