"""``dcuscope compare`` on real runs: a known injected delay found, identical configs found the same,
the gate's exit codes, the table, JSON and Markdown.

Two ``dcuscope run`` pipelines of one config, A and B, run at the same time (so that they share the
machine's load); then A2, a third of that config, beside C, whose identity sleeps 2 ms more per
frame. Each comparison is of two runs made side by side. Last, alone, "plain": that pipeline without
the identity, a different pipeline. The model-free pipeline keeps
CPU contention low; the module runs alone (a timing comparison beside five busy workers compares
the workers)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from dcuscope.commands.compareformat import ms_digits
from tests.conftest import REPO, cli_env, run_cli

pytestmark = pytest.mark.alone

FRAMES = 200
"""Per run, at 60 frames/s: p90 keeps 20 frames beyond it, twice the MIN_TAIL a verdict needs
(dcuscope/model/compare.py), so every figure the tests judge gets a verdict, not 'too few frames'."""
CONFIG = """\
node: DCU-1
launch: videotestsrc is-live=true pattern=ball ! video/x-raw,width=320,height=240,framerate=60/1 !
  identity name=work sleep-time={sleep_us} ! videoconvert name=convert ! fakesink name=sink
"""
"""One streaming thread: a queue's hand-over to its thread, with three pipelines on two cores, differs
from one run to the next by more than the noise threshold (docs/compare.md: what intervals do not hold)."""
EXTRA_MS = 2.0
PLAIN = """\
node: DCU-1
launch: videotestsrc is-live=true pattern=ball ! video/x-raw,width=320,height=240,framerate=60/1 !
  videoconvert name=convert ! fakesink name=sink
"""
"""CONFIG without its identity: another pipeline, whose frames end 2-4 ms sooner (no sleep)."""


@pytest.fixture(scope="module")
def traces(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp("compare")
    out = {}
    for together in ((("a", 2000), ("b", 2000)), (("a2", 2000), ("c", 2000 + int(EXTRA_MS * 1000)))):
        procs = []
        for name, sleep_us in together:
            config = tmp / f"{name}.yaml"
            config.write_text(CONFIG.format(sleep_us=sleep_us))
            out[name] = tmp / f"{name}.trace.jsonl"
            procs.append(subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config), "--probes",
                                           "--trace", str(out[name]), "-n", str(FRAMES), "-q"], cwd=REPO,
                                          env=cli_env(), stderr=subprocess.PIPE, text=True))
        for p in procs:
            assert p.wait(timeout=120) == 0, p.stderr.read()
    (tmp / "plain.yaml").write_text(PLAIN)
    out["plain"] = tmp / "plain.trace.jsonl"
    run = run_cli("run", tmp / "plain.yaml", "--probes", "--trace", out["plain"], "-n", "100", "-q")
    assert run.returncode == 0, run.stderr
    return out


def compare_json(*args) -> dict:
    result = run_cli("compare", *args, "--json")
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def row(doc: dict, stage: str, kind: str = "delay") -> dict:
    return next(r for r in doc["rows"] if r["stage"] == stage and r["kind"] == kind)


def test_two_more_milliseconds_of_sleep_are_found_where_they_are(traces):
    doc = compare_json(traces["a2"], traces["c"])
    work = row(doc, "work")["changes"][1]
    e2e = row(doc, "e2e")["changes"][1]
    for c in (work["mean"], work["p50"], work["p90"], e2e["mean"], e2e["p50"]):
        # The interval holds the 2 ms, give or take what the two runs' sleeps overshoot on a loaded
        # machine (CI runs measured 2.18-2.29 ms, and 1.72-1.87 ms where the baseline's sleeps
        # overshot more), and is far from 0.
        assert c["verdict"] == "slower" and 1.0 < c["low"] < EXTRA_MS * 1.2 and EXTRA_MS * 0.8 < c["high"] < 3, c
    assert row(doc, "convert")["changes"][1]["p50"]["verdict"] == "no significant change"
    verdict = doc["verdicts"][1]
    assert verdict["verdict"] == "slower" and verdict["slower"][0].startswith(("work", "e2e")), verdict
    assert all(name.split(".")[0] in ("work", "e2e") for name in verdict["slower"]), verdict


def test_identical_configs_show_no_significant_change(traces):
    doc = compare_json(traces["a"], traces["b"])
    assert doc["verdicts"][1]["verdict"] == "no significant change", doc["verdicts"][1]
    for r in doc["rows"]:
        if r["stage"] in ("work", "e2e"):
            c = r["changes"][1]["p50"]
            assert c["low"] - 0.1 < 0 < c["high"] + 0.1, (r["stage"], c)  # within 0.1 ms of no change
    assert [i["frames"] for i in doc["inputs"]] == [FRAMES, FRAMES]


def test_the_gate_exits_0_1_2_with_one_line_each(traces):
    a, b, c = traces["a"], traces["b"], traces["c"]
    ok = run_cli("compare", a, b, "--fail-if", "work.p50 > +5%", "--fail-if", "e2e.p50 > +1ms")
    assert ok.returncode == 0, ok.stderr
    assert [line.startswith("dcuscope: gate passed: ") for line in ok.stderr.splitlines()] == [True, True]

    bad = run_cli("compare", a, b, c, "--fail-if", "work.p50 > +1ms", "--fail-if", "e2e.mean > +50%")
    assert bad.returncode == 1
    lines = bad.stderr.splitlines()
    assert len(lines) == 4, lines
    assert sum("FAILED" in line for line in lines) == 2 and all("c vs a" in line for line in lines if "FAILED" in line)
    assert "the whole interval is past the bound" in bad.stderr

    # A change that may be under the bound passes: 2 ms more is not surely more than 2.5 ms more.
    assert run_cli("compare", traces["a2"], c, "--fail-if", "work.mean > +2.5ms").returncode == 0

    for args, says in ((("work.p50 > 5",), "expected STAGE[.KIND].FIGURE OP VALUE"),
                       (("nosuch.p99 > +5%",), "no delay of stage 'nosuch'"),
                       (("work.p75 > +5%",), "the figure must be one of"),
                       (("work.wait.p50 > +5%",), "BASE's p50 is 0 ms")):
        result = run_cli("compare", a, c, "--fail-if", *args)
        assert result.returncode == 2 and says in result.stderr, (args, result.stderr)
        assert len(result.stderr.splitlines()) == 1 and not result.stdout


def test_bad_inputs_exit_2_with_one_line(traces, tmp_path):
    (tmp_path / "junk.jsonl").write_text("not json\n")
    for args, says in (((traces["a"],), "give BASE and at least one NEW"),
                       ((traces["a"], tmp_path / "missing.jsonl"), "cannot read trace file"),
                       ((traces["a"], tmp_path / "junk.jsonl"), "junk.jsonl"),
                       ((traces["a"], "session:1"), "give --db"),
                       ((traces["a"], "7"), "session:7 with --db"),
                       ((traces["a"], "session:1", "--db", tmp_path / "none.db"), "no such database"),
                       ((traces["a"], traces["b"], "--node", "DCU-9"), "has no node 'DCU-9' (it has DCU-1)")):
        result = run_cli("compare", *args)
        assert result.returncode == 2 and says in result.stderr, (args, result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def test_table_and_markdown_put_inputs_side_by_side(traces):
    table = run_cli("compare", traces["a"], traces["b"], traces["c"])
    assert table.returncode == 0, table.stderr
    lines = table.stdout.splitlines()
    work = lines.index(next(line for line in lines if line.startswith("work ")))
    assert [line.split()[0] for line in lines[work + 1:work + 6]] == ["a", "b", "change", "c", "change"]
    assert "▲" in lines[work + 5] and "c vs a: SLOWER" in table.stdout and "b vs a: no significant change" in table.stdout
    md = run_cli("compare", traces["a"], traces["c"], "--markdown").stdout
    assert md.startswith("### dcuscope compare") and "| stage | input | frames | mean ms | p50 ms | p90 ms | p99 ms |" in md
    assert f"| work | `a` | {FRAMES} |" in md and "**c vs a: SLOWER" in md


def test_the_table_and_markdown_give_each_change_in_ms_beside_percent(traces):
    doc = compare_json(traces["a2"], traces["c"])
    table = run_cli("compare", traces["a2"], traces["c"]).stdout.splitlines()
    md = run_cli("compare", traces["a2"], traces["c"], "--markdown").stdout.splitlines()
    for stage in ("work", "e2e"):
        c = row(doc, stage)["changes"][1]
        title = "end to end" if stage == "e2e" else stage
        line = table[table.index(next(t for t in table if t.startswith(title))) + 3]
        cells = next(m for m in md[md.index(next(m for m in md if m.startswith(f"| {title}"))):] if "*change*" in m)
        for figure in ("mean", "p50", "p90", "p99"):
            f = c[figure]
            assert f["delta"] > 1.0 or figure == "p99"  # 2 ms more sleep: ms that read as such (p99: too few)
            delta = f"{f['delta']:+.{ms_digits(f['delta'])}f}"  # to the µs, 3 significant digits below 0.1 ms
            text = f"{delta} ms {f['pct']:+.1f}% [{f['pct_low']:+.1f}, {f['pct_high']:+.1f}]"
            assert text in line and text in cells, (stage, figure, text, line, cells)
    assert any(t.startswith("change: NEW - BASE in ms, then in % of BASE") for t in table)


def test_different_pipelines_are_compared_only_on_the_stages_both_have(traces):
    plain, c = traces["plain"], traces["c"]
    doc = compare_json(plain, c)
    assert doc["inputs"][1]["apart"] == ["work", "e2e"], doc["inputs"]
    shared = {r["stage"] for r in doc["rows"]} - {"work", "e2e"}
    assert "convert" in shared, shared
    for r in doc["rows"]:
        compared = r["changes"][1] is not None
        assert compared == (r["stage"] in shared), (r["stage"], r["kind"], r["changes"][1])
    assert row(doc, "e2e")["values"][1]["p50"] > row(doc, "e2e")["values"][0]["p50"] + 1.5  # shown, not judged
    verdict = doc["verdicts"][1]
    assert all(name.split(".")[0] in shared for name in verdict["slower"] + verdict["faster"]), verdict
    table = run_cli("compare", plain, c).stdout.splitlines()
    for title in ("work", "end to end"):
        block = table.index(next(t for t in table if t.startswith(title)))
        assert table[block + 3].split() == ["not", "in", "both"], table[block:block + 4]
    assert f"c vs plain: different pipelines, compared on the {len(shared)} stages both have; not in both, no " \
           "verdict: work, end to end" in table
    gate = run_cli("compare", plain, c, "--fail-if", "e2e.p50 > +1ms")
    assert gate.returncode == 2 and "different pipelines" in gate.stderr and len(gate.stderr.splitlines()) == 1


def test_more_cameras_through_the_same_stages_compare_end_to_end():
    # The paper's tables of 1, 2 and 3 streams: src2, a source's stamp only NEW has, is no other pipeline.
    from dcuscope.model.compare import Input, compare
    from dcuscope.model.delays import frame_delays
    from dcuscope.model.frametable import frame_table
    from tests.probes.synth import pipeline_run

    inputs = []
    for sources in (2, 3):
        header, events, _ = pipeline_run(60, sources)
        kinds = {f"src{k}": "framestamp" for k in range(sources)}
        inputs.append(Input(label=f"{sources}", origin="synth", node=header.node, kinds=kinds,
                            fd=frame_delays(frame_table(header, events))))
    doc = compare(inputs, resamples=50)
    assert doc["inputs"][1]["apart"] == [] and row(doc, "e2e")["changes"][1] is not None, doc["inputs"]
    inputs[1].kinds = {}  # the same stage of an element of any other kind: another pipeline
    doc = compare(inputs, resamples=50)
    assert doc["inputs"][1]["apart"] == ["src2", "e2e"] and row(doc, "e2e")["changes"][1] is None
