"""The page's history view in Chromium: one DCU's per-stage p50/p99 from the store's rollups, the span
fitted to its data, a gap between two runs drawn as a gap, axes that say what they show (µs below a
millisecond) with every label whole inside the chart, the stage view's colours, the statistics of the
span as `dcuscope stats --node --since` gives them, the wheel zooming in (a finer span asked of the
relay); and a live DCU in History by itself from its raw batches, then from its rollups (on a relay
compacting every 10 s and waiting 20 s for a live run: the default's 90 s, scaled down)."""

from __future__ import annotations

import calendar
import json
import re
import time

import pytest

from dcuscope.probes.ship.simnode import synth_events
from dcuscope.relay.rollup.compute import HOUR_NS, MINUTE_NS
from dcuscope.relay.store.compaction import compact
from dcuscope.relay.store.compactor import TEST_LIVE_WAIT_ENV, rollups_within_s
from dcuscope.relay.store.engines import open_database
from dcuscope.relay.store.history import summary
from tests.conftest import run_cli
from tests.relay.helpers import RelayProcess, get_json, start_node, wait_for
from tests.relay.store.test_compaction import write_run
from tests.ui.helpers import RelayThread

NODE = "DCU-7"
FAST = "DCU-8"
"""A DCU whose stages take microseconds."""
LIVE_WAIT_S = 20.0
"""The live test's relay: --compact-after and the wait for a live run's batches (LIVE_WAIT_S is 60)."""
LIVE_SLACK_S = 60
"""How much later than its relay says a live DCU's series may come on a loaded machine."""


@pytest.fixture
def store(tmp_path):
    """Two runs of DCU-7, three minutes each, 3 hours and 1 hour ago, and one of DCU-8 (delays a
    hundredth of DCU-7's), 30 minutes ago, compacted (their rollups written)."""
    path = str(tmp_path / "relay.db")
    now = time.time_ns()
    fast = synth_events(600, 2, 25.0, 0, seed=2)
    fast["ts"] = now - 30 * MINUTE_NS + fast["ts"] // 100
    for k, (node, events) in enumerate(((NODE, synth_events(4500, 2, 25.0, now - 3 * HOUR_NS, seed=0)),
                                        (NODE, synth_events(4500, 2, 25.0, now - HOUR_NS, seed=1)), (FAST, fast))):
        run, _ = write_run(path, events)
        database = open_database(path)
        database.conn.execute("UPDATE runs SET node = ? WHERE id = ?", (node, run))
        database.close()
    database = open_database(path)
    compact(database, time.time_ns(), min_events=1)
    database.close()
    return path


def drawn(page, action) -> str:
    """Do ``action``, wait for the history it asks for to be drawn; the URL asked."""
    note = page.text_content("#history-note")
    with page.expect_response(lambda r: "/api/history?" in r.url) as answer:
        action()
    page.wait_for_function("t => document.querySelector('#history-note').textContent !== t", arg=note)
    return answer.value.url


def chart(page) -> dict:
    """The chart's geometry: its box and each text's (page px), the plot's x range (viewBox units),
    the x of every point of the frame's p99 line, the y axis' labels."""
    return page.evaluate("""() => {
      const svg = document.querySelector('#history-chart');
      const box = (r) => [r.left, r.top, r.right, r.bottom];
      const d = svg.querySelector('path.history-line[data-stage=frame][data-q=p99_ms]').getAttribute('d');
      const grid = svg.querySelector('line.grid');
      return {svg: box(svg.getBoundingClientRect()), width: svg.viewBox.baseVal.width,
              texts: [...svg.querySelectorAll('text')].map((t) => [t.textContent, box(t.getBoundingClientRect())]),
              plot: [Number(grid.getAttribute('x1')), Number(grid.getAttribute('x2'))],
              xs: [...d.matchAll(/[ML]([\\d.]+),/g)].map((m) => Number(m[1])),
              y: [...svg.querySelectorAll('text.axis-y')].map((t) => t.textContent)};
    }""")


def assert_labels_whole(geometry: dict) -> None:
    left, top, right, bottom = geometry["svg"]
    for text, (l, t, r, b) in geometry["texts"]:
        assert left <= l and r <= right and top <= t and b <= bottom, (text, (l, t, r, b), geometry["svg"])


def strokes(page) -> dict:
    """Each stage's p99 line's colour, as drawn (rgb())."""
    return page.eval_on_selector_all("path.history-line[data-q=p99_ms]",
                                     "ps => Object.fromEntries(ps.map(p => [p.dataset.stage, getComputedStyle(p).stroke]))")


def test_the_history_view_draws_rollups_with_gaps_and_the_spans_statistics(browser, store, tmp_path):
    relay = RelayThread(tmp_path / "relay.db")
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(relay.url + "/")
        with page.expect_response(lambda r: "/api/history?" in r.url):
            page.click(".tab[data-tab=history]")
        page.wait_for_selector("path.history-line", state="attached")
        assert page.input_value("#history-node") == NODE and page.input_value("#history-span") == "fit"
        # Opened fitted to the data: its first and last minutes near the plot's two ends.
        fitted = chart(page)
        (x0, x1), xs = fitted["plot"], fitted["xs"]
        assert min(xs) - x0 < 0.1 * (x1 - x0) and x1 - max(xs) < 0.1 * (x1 - x0), (xs, x0, x1)
        assert "all its data" in page.text_content("#history-note")
        assert_labels_whole(fitted)
        assert "time (UTC)" in [t for t, _ in fitted["texts"]]
        # The stage view's colours (colours.js: infer blue), by the stages' kinds.
        colours = page.evaluate("async () => { const c = await import('/colours.js'); const s = document.createElement('i');"
                                " document.body.append(s); const out = {}; for (const [k, v] of Object.entries(c.STAGE_COLOURS))"
                                " { s.style.color = v; out[k] = getComputedStyle(s).color; } s.remove(); return out; }")
        drawn_colours = strokes(page)
        assert {k: drawn_colours[k] for k in colours} == colours and colours["infer"] == "rgb(30, 136, 229)"
        swatches = page.eval_on_selector_all(".history-legend .legend-item", "es => Object.fromEntries(es.map(e => "
                                             "[e.dataset.stage, getComputedStyle(e.querySelector('.swatch')).backgroundColor]))")
        assert swatches == drawn_colours
        drawn(page, lambda: page.select_option("#history-span", "21600"))  # 6 hours
        d = page.get_attribute("path.history-line[data-stage=frame][data-q=p99_ms]", "d")
        assert d.count("M") == 2, d  # two runs, the two hours between them a gap
        stages = page.eval_on_selector_all("path.history-line[data-q=p99_ms]", "ps => ps.map(p => p.dataset.stage)")
        assert stages == ["frame", "mux", "infer", "tiler", "convert", "osd"]
        expected = summary(store, NODE, time.time_ns() - 6 * HOUR_NS, time.time_ns())
        cells = page.eval_on_selector_all(".history-table tbody tr", "rs => rs.map(r => [...r.cells].map(c => c.textContent))")
        assert [c[0] for c in cells] == [f"stage {s}" for s in expected["stages"]] + ["frame (end to end)"]
        assert int(cells[-1][1]) == expected["frame"]["count"] > 0
        assert "within 1 % of the value" in page.text_content("#history-summary")
        assert "a point per minute" in page.text_content("#history-note")
        assert_labels_whole(chart(page))
        page.screenshot(path=str(tmp_path / "history.png"), full_page=True)
        # The wheel over the chart zooms in around the pointer: a shorter span, asked again.
        box = page.locator("#history-chart").bounding_box()
        page.mouse.move(box["x"] + box["width"] * 0.9, box["y"] + box["height"] / 2)
        asked = drawn(page, lambda: page.mouse.wheel(0, -300))
        since_s = int(asked.split("since=")[1].split("s&")[0])
        assert 5 * MINUTE_NS <= since_s * 1e9 < 6 * HOUR_NS
        # A DCU of microseconds: its delay axis in µs, each label its own value.
        drawn(page, lambda: page.select_option("#history-node", FAST))
        fast = chart(page)
        assert len(set(fast["y"])) == len(fast["y"]) >= 3, fast["y"]
        assert sum(label.endswith(" µs") for label in fast["y"]) >= 2 and "0.0 ms" not in fast["y"], fast["y"]
        assert_labels_whole(fast)
    finally:
        page.close()
        relay.stop()
    assert not errors, errors


def test_the_fitted_span_ends_at_the_newest_data_never_in_the_future(browser, tmp_path):
    """A DCU whose 20 s of data ended some 20 s ago: the span opens on all of it and ends at its newest
    event (the minute the note names), not at the end of a 5-minute span running into the future."""
    path = str(tmp_path / "recent.db")
    # Its newest event some 10 s into a minute, before that minute's middle, where its point is drawn
    # unless the span ends sooner: the point then lies at the span's end.
    minute = (time.time_ns() - 25 * 10**9) // MINUTE_NS * MINUTE_NS
    events = synth_events(500, 2, 25.0, minute + 10 * 10**9 - 20 * 10**9, seed=3)
    run, _ = write_run(path, events)
    database = open_database(path)
    database.conn.execute("UPDATE runs SET node = ? WHERE id = ?", (NODE, run))
    compact(database, time.time_ns(), min_events=1)
    database.close()
    newest_ns = int(events["ts"].max())
    relay = RelayThread(tmp_path / "recent.db")
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        page.goto(relay.url + "/")
        with page.expect_response(lambda r: "/api/history?" in r.url) as answer:
            page.click(".tab[data-tab=history]")
        page.wait_for_selector("path.history-line", state="attached")
        assert answer.value.json()["history"]["newest_ns"] == newest_ns
        note = page.text_content("#history-note")
        opened_ns = time.time_ns()
        geometry = chart(page)
    finally:
        page.close()
        relay.stop()
    stamps = re.search(r"all its data, (\S+ \S+) to (\S+ \S+) UTC", note)
    assert stamps, note
    end_ns = calendar.timegm(time.strptime(stamps.group(2), "%Y-%m-%d %H:%M")) * 10**9
    assert end_ns == newest_ns // MINUTE_NS * MINUTE_NS <= opened_ns, (note, newest_ns)
    (x0, x1), xs = geometry["plot"], geometry["xs"]
    assert max(xs) == pytest.approx(x1, abs=1.0), (xs, x1)  # the newest minute at the span's end


@pytest.mark.long
def test_a_live_dcu_shows_in_history_and_stats_soon_after_its_start(browser, tmp_path, monkeypatch):
    """A relay compacting after 20 s, waiting 20 s for a live run's batches (the default: 60 s and 60 s)
    and a slow paced DCU (120 events/s, where rollups once waited for 100,000). Before its rollups come,
    the History tab, left open, lists the DCU and draws its series from its raw batches, in the stage
    view's colours, and `stats --since` counts its frames, saying which minutes were still raw; once the
    relay rolled them up, while the DCU still runs, `stats --since` answers as /api/history does."""
    db = tmp_path / "relay.db"
    monkeypatch.setenv(TEST_LIVE_WAIT_ENV, str(LIVE_WAIT_S))
    relay = RelayProcess(db, args=["--compact-after", str(LIVE_WAIT_S)])
    promised_s = rollups_within_s(LIVE_WAIT_S, LIVE_WAIT_S)
    node = start_node(relay.url, "DCU-1", tmp_path / "n.npz", frames=5 * 200, fps=5.0, sources=2, paced=True)
    started = time.monotonic()
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(relay.url + "/")
        page.wait_for_selector("#legend .legend-item[data-stage=infer]")
        live = page.eval_on_selector_all("#legend .legend-item", "es => Object.fromEntries(es.map(e => "
                                         "[e.dataset.stage, getComputedStyle(e.querySelector('.swatch')).backgroundColor]))")
        page.click(".tab[data-tab=history]")
        # The tab as left: the series come by themselves (it looks again every 15 s), from raw batches.
        page.wait_for_selector("path.history-line[data-stage=infer][data-q=p99_ms]", state="attached",
                               timeout=(promised_s + LIVE_SLACK_S) * 1000)
        early = json.loads(run_cli("stats", "--db", db, "--node", "DCU-1", "--since", "1h", "--json").stdout)
        early_rollups = get_json(relay.url + "/api/health")["compaction"]["passes"] == 0
        paths = page.eval_on_selector_all("path.history-line[data-q=p99_ms]", "ps => ps.map(p => [p.dataset.stage, p.getAttribute('d')])")
        assert [s for s, _ in paths] == ["frame", "mux", "infer", "tiler", "convert", "osd"] and all(d for _, d in paths)
        assert {k: v for k, v in strokes(page).items() if k != "frame"} == {k: live[k] for k in live if k in strokes(page)}
        assert_labels_whole(chart(page))
        # Then the rollups, while the DCU runs: the CLI and the relay read the same, between two passes.
        wait_for(lambda: json.loads(run_cli("stats", "--db", db, "--node", "DCU-1", "--since", "1h", "--json").stdout)
                 ["rows"] > 0, promised_s + LIVE_SLACK_S - (time.monotonic() - started), 2.0, "the DCU's rollups")
        assert node.poll() is None, "the DCU ended before its rollups came"
        late = run_cli("stats", "--db", db, "--node", "DCU-1", "--since", "1h", "--json")
        # The DCU stopped (its batches, even late ones on a loaded machine, all in): rollups and raw
        # batches together read alike by the CLI's code and the relay, between two compaction passes.
        node.kill()
        node.wait(10)
        ran_s = time.monotonic() - started
        until = time.time_ns()
        for _ in range(10):  # the relay's writer may still commit the batches it received last
            time.sleep(0.5)
            passes = get_json(relay.url + "/api/health")["compaction"]["passes"]
            read = summary(db, "DCU-1", until - HOUR_NS, until)  # as `stats --since` reads it
            answer = get_json(relay.url + f"/api/history?node=DCU-1&since=3600s&until_ns={until}")
            if (get_json(relay.url + "/api/health")["compaction"]["passes"] == passes
                    and read["frame"]["count"] == answer["summary"]["frame"]["count"]):
                break
    finally:
        page.close()
        node.kill()
        node.wait(10)
        relay.stop()
    assert early["frame"]["count"] > 0, early
    if early_rollups:  # no pass had run: every frame counted came from the raw batches, and it says so
        assert early["rows"] == 0 and early["raw"]["included"] and "were still raw" in early["raw"]["said"], early
    assert late.returncode == 0, late.stderr
    assert json.loads(late.stdout)["frame"]["count"] > 0
    assert 0 < read["frame"]["count"] == answer["summary"]["frame"]["count"] <= ran_s * 5 * 2, (read, answer)
    assert not errors, errors
