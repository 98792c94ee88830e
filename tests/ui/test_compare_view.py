"""The page's Compare tab in Chromium, ``/api/compare`` and ``dcuscope compare --db`` on the same stored runs:
two runs of one DCU in one session (gst-launch-1.0 traced and shipped live by ``dcuscope trace --relay``, the
second's identity sleeping 6 ms more), while a simulated DCU keeps the session live. Each run is one entry
of the page's selects; the page shows the figures the CLI prints for the same two runs, named as the CLI
names them; it opens on a figure the runs decide, its headline agreeing with the rows shown, each change in
ms and in %; two different pipelines get no verdict on what they do not share; no value label lies under a
whisker."""

from __future__ import annotations

import json
import sqlite3
import urllib.error
import urllib.request

import pytest

from dcuscope.relay.store.runs import list_sessions
from tests.conftest import run_cli
from tests.relay.helpers import finish_node, get_json, start_node, wait_for
from tests.ui.helpers import RelayThread
from tests.ui.test_browser import SHOTS

NODE = "DCU-3"
OTHER = "DCU-S"
"""A simulated DCU live from before NODE's first run to after its second: one session holds all three runs."""
FIGURES = ("mean", "p50", "p90", "p99")


def shipped(relay: RelayThread, tmp_path, sleep_us: int) -> None:
    result = run_cli("trace", "--relay", relay.url, "--node", NODE, "-o", tmp_path / f"{sleep_us}.trace.jsonl", "-q",
                     "--", "gst-launch-1.0", "-q", "videotestsrc", "num-buffers=200", "!",
                     "video/x-raw,width=160,height=120", "!", "identity", "name=work", f"sleep-time={sleep_us}", "!",
                     "videoconvert", "!", "fakesink", cwd=tmp_path)
    assert result.returncode == 0, result.stderr


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """(relay, db, session, [BASE run, NEW run] of NODE, OTHER's run)."""
    tmp = tmp_path_factory.mktemp("compare")
    relay = RelayThread(tmp / "relay.db")
    other = start_node(relay.url, OTHER, tmp / "other.npz", frames=50, linger=True)
    try:
        wait_for(lambda: any(n["node"] == OTHER for n in get_json(f"{relay.url}/api/nodes")), 30, what=f"{OTHER} live")
        shipped(relay, tmp, 2000)
        shipped(relay, tmp, 8000)
        finish_node(other)
        [session] = list_sessions(tmp / "relay.db")
        runs = [r["run"] for r in session["runs"] if r["node"] == NODE]  # by first-seen time
        [other_run] = [r["run"] for r in session["runs"] if r["node"] == OTHER]
        assert len(runs) == 2, session
        yield relay, tmp / "relay.db", session["session"], runs, other_run
    finally:
        other.kill()
        other.wait(5)
        relay.stop()


def compare_json(*args) -> dict:
    result = run_cli("compare", *args, "--json")
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_two_runs_of_one_dcu_in_one_session_show_what_the_cli_shows(browser, stored):
    relay, db, session, (base, new), other = stored
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(relay.url + "/")
        with page.expect_response(lambda r: "/api/compare?" in r.url) as answer:
            page.click(".tab[data-tab=compare]")
        assert answer.value.ok
        page.wait_for_selector(".cmp-row[data-stage=work]")
        # Each run one entry, named by its id; by default the two runs of the one DCU that has two.
        options = page.eval_on_selector_all("#compare-base option", "os => os.map(o => [o.value, o.textContent])")
        assert sorted(v for v, _ in options) == sorted([base, new, other]), options
        assert len({text for _, text in options}) == 3, options
        assert (page.input_value("#compare-base"), page.input_value("#compare-new")) == (base, new)

        # The page shows what the CLI prints for the same two runs, named as the CLI names them.
        cli = compare_json("--db", db, f"run:{base[:8]}", f"run:{new[:8]}")
        doc = get_json(answer.value.url)
        assert doc["rows"] == cli["rows"] and doc["verdicts"] == cli["verdicts"]  # same seed and resamples
        labels = [f"session {session} · {NODE} · run {run[:8]}" for run in (base, new)]
        assert [i["label"] for i in doc["inputs"]] == [i["label"] for i in cli["inputs"]] == labels
        assert dict(options)[base].startswith(labels[0]) and dict(options)[new].startswith(labels[1])
        inputs = page.text_content(".compare-inputs")
        assert all(f"{i['label']}: {i['frames']} frames" in inputs for i in cli["inputs"]), inputs
        work = next(r for r in cli["rows"] if r["stage"] == "work" and r["kind"] == "delay")
        assert work["values"][1]["p50"] > work["values"][0]["p50"] + 3  # 6 ms more (a loaded machine oversleeps both)

        # It opens on p50: a p99 of 200 frames has too few beyond it for any row to decide it.
        assert page.input_value("#compare-figure") == "p50"
        c = work["changes"][1]["p50"]
        change = f"{c['delta']:+.3f} ms · {c['pct']:+.1f} % [{c['pct_low']:+.1f}, {c['pct_high']:+.1f}]"
        assert change in page.text_content(".cmp-row[data-stage=work] .cmp-change"), change
        # Whatever the figure, the headline says "slower" (in red) exactly where a row shown is slower.
        shown_rows = [r for r in cli["rows"] if r["kind"] == "delay"]
        for figure in ("p50", "p99", "mean", "p90"):
            if figure != "p50":
                page.select_option("#compare-figure", figure)
            slower = [r["stage"] for r in shown_rows if r["changes"][1][figure]["verdict"] == "slower"]
            headline = page.text_content(".compare-verdict")
            red = page.locator(".compare-verdict .verdict-slower, .compare-verdict.verdict-slower").count()
            assert ("slower" in headline) == bool(slower) == bool(red), (figure, slower, headline)
            assert figure != "p99" or not slower  # p99: nothing decided, nothing red
        for figure in ("mean", "p50"):
            page.select_option("#compare-figure", figure)
            for r in (r for r in cli["rows"] if r["kind"] == "delay"):
                for role, v in zip(("base", "new"), r["values"]):
                    track = page.locator(f".cmp-row[data-stage={r['stage']}] .cmp-track.{role}")
                    shown = float(track.locator(".cmp-val").inner_text().removesuffix(" ms"))
                    assert abs(shown - v[figure]) <= 0.0005 + 1e-9, (r["stage"], role, figure, shown, v)
                    assert track.get_attribute("title").endswith(f": {v['frames']} frames")

        # The headline speaks of the figure shown, the whole table's verdict beside it, labelled as such.
        page.select_option("#compare-figure", "p99")  # of 200 frames: every row too few
        assert "p99 of delay, NEW against BASE: no row decided: too few frames" in page.text_content(".compare-shown")
        whole = page.text_content(".compare-whole")
        assert "Over the whole table (all" in whole and cli["verdicts"][1]["verdict"] in whole
        page.select_option("#compare-figure", "p50")
        assert work["changes"][1]["p50"]["verdict"] == "slower"
        shown = page.locator(".compare-shown")
        assert "p50 of delay, NEW against BASE: slower in " in shown.inner_text() and "work" in shown.inner_text()
        assert "verdict-slower" in shown.get_attribute("class")

        # No value label lies under a whisker or a bar, whatever the figure.
        for figure in FIGURES:
            page.select_option("#compare-figure", figure)
            overlaps = page.evaluate("""() => {
              const box = (e) => e.getBoundingClientRect();
              const cross = (a, b) => a.left < b.right && b.left < a.right && a.top < b.bottom && b.top < a.bottom;
              const labels = [...document.querySelectorAll('.cmp-val')].map(box);
              const marks = [...document.querySelectorAll('.cmp-plot .ci, .cmp-bar')].map(box);
              return [labels.length, document.querySelectorAll('.cmp-plot .ci').length,
                      labels.flatMap((l) => marks.filter((m) => m.width > 0 && cross(l, m))).length];
            }""")
            assert overlaps[0] > 0 and overlaps[1] > 0 and overlaps[2] == 0, (figure, overlaps)
        page.select_option("#compare-figure", "p50")
        SHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SHOTS / "compare-view.png"))

        # Where no DCU has two runs, the newest two of one pipeline; else the newest two, said to differ.
        picks = page.evaluate("""async () => {
          const m = await import('/compareview.js');
          const run = (run, node, first, stages) => ({run, node, first, stages});
          const pick = (runs) => m.defaultPair(runs).map((r) => (typeof r === 'string' ? r : r.run));
          return [pick([run('d', 'B', 4, ['x']), run('c', 'A', 3, ['y']), run('b', 'C', 2, ['x']),
                        run('a', 'A', 1, ['y'])]),
                  pick([run('c', 'A', 3, ['x']), run('b', 'B', 2, ['y']), run('a', 'C', 1, ['x'])]),
                  pick([run('b', 'A', 2, ['x']), run('a', 'B', 1, ['y'])])];
        }""")
        assert picks == [["a", "c", "dcu"], ["a", "c", "pipeline"], ["a", "b", "different"]]
        assert "different pipelines" not in page.text_content(".compare-inputs")
        with page.expect_response(lambda r: f"/api/compare?base={other}&new={new}" in r.url) as answer:
            page.select_option("#compare-base", other)
        assert answer.value.ok
        page.wait_for_function("document.querySelector('.compare-inputs').textContent.includes('different pipelines')")
        assert f"BASE session {session} · {OTHER}: 100 frames" in page.text_content(".compare-inputs")
        # No stage in both: every row's verdict withheld, end to end too, and nothing red or green.
        changes = page.eval_on_selector_all(".cmp-change", "cs => cs.map(c => [c.className, c.textContent])")
        assert changes and all(cls == "cmp-change verdict-apart" for cls, _ in changes), changes
        assert page.text_content(".cmp-row[data-stage=e2e] .cmp-change") == "not in both: the stages differ"
        assert "no row in both runs" in page.text_content(".compare-shown")
        assert page.locator("#compare-body .verdict-slower, #compare-body .verdict-faster").count() == 0
    finally:
        page.close()
    assert not errors, errors


def answer(url: str) -> tuple[int, dict]:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def test_the_api_names_runs_by_id_and_says_what_is_wrong(stored):
    relay, _, session, (base, new), other = stored
    ids = (base, new, other)
    absent = next(p for p in (f"{k:06x}" for k in range(1 << 12)) if not any(r.startswith(p) for r in ids))
    for query, status, says in (
            (f"base={base[:7].upper()}&new={new}", 200, ""),
            (f"base={session}&base_node={OTHER}&new={new}", 200, ""),
            (f"base={session}&base_node={NODE}&new={new}", 400, f"holds 2 runs of node '{NODE}': name one as base=RUN"),
            (f"base={base}&new={new[:5]}", 400, "new=RUN is required"),
            (f"base=zz{base[2:]}&new={new}", 400, "base=RUN is required"),
            (f"base={base}", 400, "new=RUN is required"),
            (f"base={absent}&new={new}", 404, f"no stored run {absent}"),
            (f"base={base}&new=99&new_node={NODE}", 404, "no session or run 99"),
            (f"base={base}&new={session}&new_node=NOPE", 404, f"session {session} has no node 'NOPE'"),
            (f"base={base}&new={new}&noise=200", 400, "noise=PCT")):
        status_got, body = answer(f"{relay.url}/api/compare?{query}")
        assert status_got == status and says in body.get("error", ""), (query, status_got, body)
        if status == 200:
            assert body["inputs"][1]["label"] == f"session {session} · {NODE} · run {new[:8]}", body["inputs"]
            assert body["inputs"][0]["label"] in (f"session {session} · {OTHER}",
                                                  f"session {session} · {NODE} · run {base[:8]}")


def test_the_cli_says_each_thing_once_in_short_unique_labels(stored):
    _, db, session, (base, new), other = stored
    table = run_cli("compare", "--db", db, f"run:{base[:8]}", f"run:{new[:8]}")
    assert table.returncode == 0, table.stderr
    head = table.stdout.splitlines()[:2]
    assert head == [f"BASE session {session} · {NODE} · run {base[:8]}: {db}, 200 complete frames",
                    f"NEW  session {session} · {NODE} · run {new[:8]}: {db}, 200 complete frames"], head
    same = compare_json("--db", db, f"session:{session}", f"session:{session}", "--node", OTHER)
    assert [i["label"] for i in same["inputs"]] == [f"session {session} · {OTHER}", f"session {session} · {OTHER} (2)"]
    assert [i["origin"] for i in same["inputs"]] == [f"{db}, run {other[:8]}"] * 2
    twins = run_cli("compare", "--db", db, f"session:{session}", f"run:{new}", "--node", NODE)
    assert twins.returncode == 2 and f"name one as run:{base[:8]} or run:{new[:8]}" in twins.stderr, twins.stderr


def test_a_prefix_of_two_runs_asks_for_more_digits(stored):
    relay, db, session, (base, new), _ = stored
    # A run the relay refused keeps its row: a prefix may begin its id and another's.
    twin = base[:6] + ("1" if base[6] == "0" else "0") + base[7:]
    with sqlite3.connect(db, timeout=10) as conn:
        conn.execute("INSERT INTO runs (id, session, node, header, first_seen_ns, last_seen_ns, rejected) "
                     "SELECT ?, session, node, header, 1, 1, 'refused' FROM runs WHERE id = ?", (twin, base))
    status, body = answer(f"{relay.url}/api/compare?base={base[:6]}&new={new}")
    assert status == 400 and body["error"] == f"base={base[:6]} begins 2 run ids: give more digits", body
    cli = run_cli("compare", "--db", db, f"run:{base[:6]}", f"run:{new}")
    assert cli.returncode == 2 and f"run:{base[:6]} begins 2 run ids" in cli.stderr, cli.stderr
