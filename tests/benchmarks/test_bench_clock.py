"""benchmarks/bench_clock.py: a case whose relay never gave an estimate is n/a with the reason in
its row, and the --quick run (one case, both transports, on loopback) prints its rows and table."""

from __future__ import annotations

from benchmarks.bench_clock import FIGURES, Run, print_table
from benchmarks.figures import NA
from tests.benchmarks.smoke import assert_every_na_has_a_reason, assert_ran, json_lines, run_benchmark

HEAD = "path | transport | via | offset_ms | drift_ppm | reads | " + " | ".join(FIGURES)


def test_a_case_without_an_estimate_is_n_a_with_the_reason(capsys):
    unread = Run("udp", 37_000_000, 50.0, "loopback", 8.0)
    unread.unread = "the relay applied no estimate (applied: none)"
    read = Run("websocket", 0, 0.0, "loopback", 8.0, errors_ns=[1500, -900], stated_ns=[4000, 2000], via="websocket")
    rows = [unread.row(), read.row()]
    assert rows[0]["reads"] == 0 and rows[0]["via"] == NA("the node did not say")
    assert all(rows[0][key] == NA("no estimate read: the relay applied no estimate (applied: none)") for key in FIGURES)
    assert rows[1]["err_max_us"] == 1.5 and rows[1]["inside"] is True
    print_table(rows)
    out = capsys.readouterr().out.splitlines()
    assert out[0] == HEAD and len(out) == 4
    assert out[2].startswith("loopback | udp | n/a (the node did not say) | 37.0 | 50.0 | 0 | n/a (no estimate read")
    assert out[3] == "loopback | websocket | websocket | 0.0 | 0.0 | 2 | 1.5 | -0.9 | 4.0 | 2.0 | True"
    assert_every_na_has_a_reason("\n".join(out))


def test_quick_mode_prints_a_row_per_transport_and_the_table():
    done = run_benchmark("bench_clock.py", "--quick", timeout=90)
    assert_ran(done, codes=(0, 1))  # 1: the truth fell outside the stated bound once: a finding, not a failure
    rows = json_lines(done.stdout)
    assert [(r["path"], r["transport"], r["offset_ms"], r["drift_ppm"]) for r in rows] == [
        ("loopback", "websocket", 37.0, 50.0), ("loopback", "udp", 37.0, 50.0)]
    assert all(set(FIGURES) <= set(r) for r in rows)
    table = done.stdout.split("\n\n", 1)[1].splitlines()
    assert table[0] == HEAD and len(table) == 4 and table[2].startswith("loopback | websocket |")
