"""The compiled core under AddressSanitizer and UndefinedBehaviorSanitizer: real batches and 4 s of
hostile ones through decoding, merging, judging and summarizing (scripts/fuzz_core.sh, gcc's build of the harness
with its own driver), no finding; and a planted overflow is found, so the run can fail."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO, cli_env
from tests.model.fuzz import seeds
from tests.model.planted import planted_sources

SECONDS = 4


def fuzz(seed_dir, seconds: float, core=None) -> subprocess.CompletedProcess:
    env = dict(cli_env(), FUZZ_DRIVER="1", PYTHON=sys.executable)
    if core is not None:
        env["CORE_DIR"] = str(core)
    return subprocess.run(["bash", str(REPO / "scripts" / "fuzz_core.sh"), str(seconds), str(seed_dir)], env=env,
                          capture_output=True, text=True, timeout=seconds + 120, cwd=REPO)


@pytest.fixture(scope="module")
def seed_dir(tmp_path_factory, real_traces):
    folder = tmp_path_factory.mktemp("seeds")
    assert len(seeds.write(folder, real_traces)) >= 15
    return folder


def test_real_and_hostile_batches_find_nothing_in_the_sanitized_core(seed_dir):
    done = fuzz(seed_dir, SECONDS)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-6000:]
    runs, merged, judged, pushed, summarized, gathered = (int(w) for w in done.stdout.split()[1:12:2])
    assert "no finding" in done.stdout and runs > 10_000 and merged > 1_000 and judged == pushed == merged, done.stdout
    assert summarized > 2 * judged, done.stdout  # the delays and frame delays of each judged table, and raw bytes
    assert gathered == judged, done.stdout  # each judged table's series


def test_a_planted_overflow_is_found(seed_dir, tmp_path):
    """A merge that opens frames past the rows it was given writes out of its arrays: caught at once."""
    done = fuzz(seed_dir, 2, planted_sources(tmp_path, "merge.c", "if (rows >= rows_cap || ", "if ("))
    assert done.returncode != 0 and "ERROR: AddressSanitizer: heap-buffer-overflow" in done.stderr, done.stderr[-3000:]
