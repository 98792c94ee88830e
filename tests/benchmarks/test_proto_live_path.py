"""Issue 50's prototype (benchmarks/proto_live_path.py): its compiled merge is held to numpy's, and
it measures every way it compares."""

from __future__ import annotations

import re

import numpy as np
import pytest

from benchmarks import proto_live_path as proto
from tests.benchmarks.smoke import assert_ran, run_benchmark


def test_the_compiled_merge_leaves_a_run_where_numpys_does():
    proto.check_native_equals_numpy(runs=1, seconds=3.0)


def test_the_equivalence_check_fails_on_a_merge_that_keeps_the_latest_time(tmp_path, monkeypatch):
    """The check can fail: a merge keeping each cell's latest time instead of its earliest is caught."""
    source = (proto.HERE / "native_merge.c").read_text()
    wrong = source.replace("e->ts < c[e->point]", "e->ts > c[e->point]")
    assert wrong != source
    (tmp_path / "native_merge.c").write_text(wrong)
    monkeypatch.setattr(proto, "HERE", tmp_path)
    with pytest.raises(AssertionError):
        proto.check_native_equals_numpy(runs=1, seconds=3.0)


def test_the_prototype_prints_every_way_per_event_and_per_batch():
    done = run_benchmark("proto_live_path.py", "--quick")
    assert_ran(done)
    rows = {tuple(m.group(1, 2)): float(m.group(3)) for m in
            re.finditer(r"^  (today|native|node pairs|node pairs, native) +(relay|node) +([\d.]+) +\d+ +[\d,]+", done.stdout, re.M)}
    assert set(rows) == {("today", "relay"), ("native", "relay"), ("node pairs", "node"), ("node pairs", "relay"),
                         ("node pairs, native", "node"), ("node pairs, native", "relay")}, done.stdout
    assert all(np.isfinite(v) and v > 0 for v in rows.values())


def test_the_floor_measures_a_real_websocket_per_message():
    done = run_benchmark("proto_live_path.py", "--floor", "--quick")
    assert_ran(done)
    assert re.search(r"400 messages of 1900 bytes over 2 connections: [\d.]+ µs of server CPU per message", done.stdout), done.stdout
