"""What DCUs run, checked here without them (issue 62; scripts/platforms.sh runs the rest in root
filesystems): nothing newer than Python 3.10 anywhere in the code, and the native library
cross-compiled for aarch64 (Jetson) against Debian's arm64 GStreamer headers."""

from __future__ import annotations

import asyncio
import shutil
import subprocess
import sys
from pathlib import Path

from dcuscope.core import cbuild
from tests.conftest import REPO

CROSS_CC = "aarch64-linux-gnu-gcc"
ARM64_PKG_CONFIG = "/usr/lib/aarch64-linux-gnu/pkgconfig"
EM_AARCH64 = 183
FOLDERS = ("core", "dcuscope", "pipeline", "plugins", "probes", "relay", "ui", "benchmarks", "scripts", "tests")


def test_nothing_needs_a_python_newer_than_3_10():
    """vermin reads every module for syntax, modules, members and keywords by the Python version that
    brought them: any newer than 3.10 (Ubuntu 22.04, JetPack 6) fails, naming the file and the feature."""
    found = subprocess.run([str(Path(sys.executable).with_name("vermin")), "--target=3.10-", "--violations", "--no-tips",
                            "--eval-annotations", "--exclude-regex", r"(^|/)(\.venv|build|node_modules|_build)/",
                            *FOLDERS, "setup.py"], cwd=REPO, capture_output=True, text=True, timeout=240)
    assert found.returncode == 0, found.stdout[-4000:] + found.stderr[-2000:]
    assert "Minimum required versions: 3.10" in found.stdout, found.stdout[-2000:]


def test_python_3_10_gets_the_backports_it_needs():
    """tomllib's backport is a dependency where it is needed, and requires-python admits 3.10."""
    from dcuscope.core.pycompat import tomllib

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert project["requires-python"] == ">=3.10"
    assert "tomli>=2.0; python_version < '3.11'" in project["dependencies"]


def elf_machine(library: Path) -> int:
    head = library.read_bytes()[:20]
    assert head[:4] == b"\x7fELF", head
    return int.from_bytes(head[18:20], "little")


def test_the_native_library_cross_compiles_for_aarch64(tmp_path, monkeypatch):
    """The tracer and tracepoints built for aarch64 against arm64's GStreamer (libgstreamer1.0-dev:arm64,
    multiarch), and the compiled core: both ELF files for AArch64, the tracer linking GStreamer."""
    assert shutil.which(CROSS_CC), f"{CROSS_CC} is missing (make setup installs gcc-aarch64-linux-gnu)"
    assert Path(ARM64_PKG_CONFIG, "gstreamer-1.0.pc").is_file(), "libgstreamer1.0-dev:arm64 is missing (make setup)"
    monkeypatch.setenv("CC", CROSS_CC)
    monkeypatch.setenv("PKG_CONFIG_LIBDIR", f"{ARM64_PKG_CONFIG}:/usr/share/pkgconfig")
    probes = cbuild.compile_library(REPO / "probes" / "capture" / "c", tmp_path / cbuild.LIBRARY_NAME)
    core = cbuild.compile_library(REPO / "dcuscope" / "model" / "c", tmp_path / cbuild.CORE.name, cbuild.CORE)
    assert elf_machine(probes) == elf_machine(core) == EM_AARCH64
    needed = subprocess.run(["aarch64-linux-gnu-readelf", "-d", str(probes)], capture_output=True, text=True).stdout
    assert "libgstreamer-1.0.so.0" in needed, needed


def test_python_3_10_s_deadline_times_out_as_asyncio_timeout_does():
    """:class:`Deadline` (``timeout`` on 3.10) beside 3.11's ``asyncio.timeout``: the same outcome for a
    wait past its deadline, one within it, no deadline, and a cancellation that is not the deadline's."""
    from dcuscope.core.pycompat import ASYNC_TIMEOUTS, Deadline

    async def outcome(make, delay, sleep_s: float, cancel_after: float | None = None) -> str:
        async def body() -> str:
            try:
                async with make(delay):
                    await asyncio.sleep(sleep_s)
                return "done"
            except ASYNC_TIMEOUTS:
                return "timed out"

        task = asyncio.ensure_future(body())
        if cancel_after is not None:
            await asyncio.sleep(cancel_after)
            task.cancel()
        try:
            return await task
        except asyncio.CancelledError:
            return "cancelled"

    cases = [(0.05, 5.0, None), (5.0, 0.01, None), (None, 0.05, None), (5.0, 5.0, 0.05), (0, 0.5, None)]
    native = getattr(asyncio, "timeout", None)  # Python 3.11 and later
    for delay, sleep_s, cancel_after in cases if native else []:
        ours = asyncio.run(outcome(Deadline, delay, sleep_s, cancel_after))
        theirs = asyncio.run(outcome(native, delay, sleep_s, cancel_after))
        assert ours == theirs, (delay, sleep_s, cancel_after, ours, theirs)
    assert [asyncio.run(outcome(Deadline, *c)) for c in cases] == ["timed out", "done", "done", "cancelled", "timed out"]


def test_platforms_script_lists_its_platforms_and_refuses_an_unknown_one():
    """scripts/platforms.sh (not run by make test: it downloads root filesystems) says what each
    platform checks, and an unknown name is one line and exit status 2, before anything is built."""
    listed = subprocess.run(["bash", "scripts/platforms.sh", "--list"], cwd=REPO, capture_output=True, text=True,
                            timeout=30)
    assert listed.returncode == 0, listed.stderr
    assert [line.split()[0] for line in listed.stdout.splitlines() if line[:2] == "  " and line[2] != " "] == \
        ["bullseye", "trixie", "arm64"], listed.stdout
    wrong = subprocess.run(["bash", "scripts/platforms.sh", "jetson"], cwd=REPO, capture_output=True, text=True,
                           timeout=30)
    assert wrong.returncode == 2 and wrong.stdout == "", (wrong.returncode, wrong.stdout)
    assert wrong.stderr.strip() == "platforms.sh: unknown platform 'jetson' (bullseye, trixie, arm64 or all; --help)"
