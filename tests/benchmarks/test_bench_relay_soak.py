"""benchmarks/bench_relay_soak.py --quick: a node restarting 20 times with its old connection left
open, and the relay's resident memory after each restart.

Besides the output being sane, the verdict must hold: the relay's RSS is flat once warmed up. Before
relay.heap and the cycle broken in RelayState.release, every released run's live state stayed in
memory until a full garbage collection, and glibc's heap kept the pages: the quick run grew by
~1.2 x one run's raw payload per restart (1.7 MB) until a collection freed a heap of dead runs at
once (the slope of a run could then come out negative), and its RSS high-water mark rose by ~15
payloads after restart 5, every time. The bounds are relative to the payload (not to this
machine's speed), and generous: a few MB of allocator noise pass, one run's worth kept per restart
does not. It runs on each store engine (~10 s each): the PostgreSQL one on a server of its own,
durable as users run it.
"""

from __future__ import annotations

import re

import pytest

from tests.benchmarks.smoke import assert_ran, json_lines, run_benchmark

GROWTH_PER_PAYLOAD = 0.25
"""Growth of RSS per restart (Theil-Sen) over restarts 5..20, as a share of one run's raw payload."""
HWM_PAYLOADS = 8.0
"""How much the RSS high-water mark may rise after restart 5, in runs' raw payloads (the peak of one
restart's transients recurs; it rises when runs' memory is kept: then by ~15 payloads in 20 restarts).
A loaded machine's transients reach further: a fresh-clone run at a load of 12 rose by 6.1 payloads
(a run whose live state peaked at 2.3 times the others', its RSS back to the warm figure after)."""


@pytest.mark.long
@pytest.mark.parametrize("store", ["sqlite", "postgresql"])
def test_quick_soak_prints_a_row_per_restart_and_the_relays_memory_stays_flat(store):
    done = run_benchmark("bench_relay_soak.py", "--quick", "--store", store, timeout=240)
    assert_ran(done)
    rows = [line.split() for line in done.stdout.splitlines() if re.match(r"\s+\d+\s+\d", line)]
    assert [int(r[0]) for r in rows] == list(range(21)), done.stdout  # the first run, then 20 restarts
    rss = [float(r[1]) for r in rows]
    assert all(20 < x < 2000 for x in rss), rss
    # The relay says it holds one run (the newest): every former one was released as the new one took over.
    assert all(int(r[4]) == 1 for r in rows), done.stdout
    [line] = json_lines(done.stdout)
    v = line["verdict"]
    assert v["restarts"] == 20 and v["rss_at_warm_mb"] == rss[5] and v["rss_max_mb"] == max(rss[5:])
    assert 1.0 < v["run_payload_mb"] < 2.0  # 60,000 events x 24 B
    payload = v["run_payload_mb"]
    assert v["growth_mb_per_restart"] < GROWTH_PER_PAYLOAD * payload, done.stdout
    assert v["hwm_growth_mb"] < HWM_PAYLOADS * payload, done.stdout
    assert "verdict: RSS" in done.stdout
    assert line["store"] == store and done.stdout.splitlines()[1].startswith(f"store {store}: ")
    if store == "postgresql":
        assert "fsync=on synchronous_commit=on" in done.stdout.splitlines()[1]
