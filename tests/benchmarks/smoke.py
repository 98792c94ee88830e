"""Running a benchmark as a user does, and checking what every benchmark promises of its output:
each n/a comes with its reason, and one that cannot run says why in one line."""

from __future__ import annotations

import json
import re
import subprocess
import sys

from tests.conftest import REPO, cli_env

NOTE = re.compile(r"n/a \[(\d+)\]: \S")
"""A footnote under a table: ``n/a [k]: reason``."""


def run_benchmark(script: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``python benchmarks/SCRIPT ARGS`` from the repository, in its own process."""
    return subprocess.run([sys.executable, str(REPO / "benchmarks" / script), *args], cwd=REPO, env=cli_env(),
                          capture_output=True, text=True, timeout=timeout)


def assert_every_na_has_a_reason(text: str) -> None:
    """Every ``n/a`` in ``text`` is ``n/a (reason)``, or ``n/a [k]`` with a ``n/a [k]: reason`` line."""
    notes = set(NOTE.findall(text))
    for m in re.finditer("n/a", text):
        after = text[m.end():]
        note = re.match(r" \[(\d+)\]", after)
        explained = re.match(r" \([^)\s]", after) or (note and note.group(1) in notes)
        assert explained, f"an n/a without its reason: {text[max(0, m.start() - 80):m.end() + 40]!r}"


def assert_ran(done: subprocess.CompletedProcess, codes: tuple[int, ...] = (0,)) -> None:
    """It ended with one of ``codes``, without a traceback, and its n/a's have their reasons."""
    assert done.returncode in codes, done.stderr[-3000:]
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    assert_every_na_has_a_reason(done.stdout)
    assert_every_na_has_a_reason(done.stderr)


def assert_cannot_run(done: subprocess.CompletedProcess, script: str, why: str) -> None:
    """It said in one line on stderr, with status 2 and no traceback, that it cannot run and ``why``."""
    assert done.returncode == 2, (done.returncode, done.stderr[-3000:])
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr[-3000:]
    assert lines[0].startswith(f"{script}: cannot run: ") and why in lines[0], lines[0]


def json_lines(text: str) -> list[dict]:
    """The lines of ``text`` that are JSON objects, parsed."""
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]
