"""Issue 50's prototypes (benchmarks/proto_live_path.py) measure every way they compare."""

from __future__ import annotations

import re

import numpy as np

from tests.benchmarks.smoke import assert_ran, run_benchmark


def test_the_prototypes_print_every_way_per_event_and_per_batch():
    done = run_benchmark("proto_live_path.py", "--quick")
    assert_ran(done)
    rows = {tuple(m.group(1, 2)): float(m.group(3)) for m in re.finditer(
        r"^  (numpy merge|compiled merge|node pairs|node pairs, compiled) +(relay|node) +([\d.]+) +\d+ +[\d,]+",
        done.stdout, re.M)}
    assert set(rows) == {("numpy merge", "relay"), ("compiled merge", "relay"), ("node pairs", "node"),
                         ("node pairs", "relay"), ("node pairs, compiled", "node"), ("node pairs, compiled", "relay")}, \
        done.stdout
    assert all(np.isfinite(v) and v > 0 for v in rows.values())


def test_the_floor_measures_a_real_websocket_per_message():
    done = run_benchmark("proto_live_path.py", "--floor", "--quick")
    assert_ran(done)
    assert re.search(r"400 messages of 1900 bytes over 2 connections: [\d.]+ µs of server CPU per message", done.stdout), \
        done.stdout
