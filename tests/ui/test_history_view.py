"""The page's history view in Chromium: one DCU's per-stage p50/p99 from the store's rollups, a gap
between two runs drawn as a gap, the statistics of the span as `dcuscope stats --node --since`
gives them, the wheel zooming in (a finer span asked of the relay)."""

from __future__ import annotations

import time

import pytest

from probes.ship.simnode import synth_events
from relay.rollup.compute import HOUR_NS, MINUTE_NS
from relay.store.history import summary
from relay.store.compaction import compact
from relay.store.engines import open_database
from tests.relay.test_compaction import write_run
from tests.ui.helpers import RelayThread

NODE = "DCU-7"


@pytest.fixture
def store(tmp_path):
    """Two runs of DCU-7, three minutes each, 3 hours and 1 hour ago, compacted (their rollups written)."""
    path = str(tmp_path / "relay.db")
    now = time.time_ns()
    for k, ago in enumerate((3 * HOUR_NS, HOUR_NS)):
        run, _ = write_run(path, synth_events(4500, 2, 25.0, now - ago, seed=k))
        database = open_database(path)
        database.conn.execute("UPDATE runs SET node = ? WHERE id = ?", (NODE, run))
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


def test_the_history_view_draws_rollups_with_gaps_and_the_spans_statistics(browser, store, tmp_path):
    relay = RelayThread(tmp_path / "relay.db")
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(relay.url + "/")
        with page.expect_response(lambda r: "/api/history?" in r.url):
            page.click(".tab[data-tab=history]")
        assert page.input_value("#history-node") == NODE
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
        page.screenshot(path=str(tmp_path / "history.png"), full_page=True)
        # The wheel over the chart zooms in around the pointer: a shorter span, asked again.
        box = page.locator("#history-chart").bounding_box()
        page.mouse.move(box["x"] + box["width"] * 0.9, box["y"] + box["height"] / 2)
        asked = drawn(page, lambda: page.mouse.wheel(0, -300))
        since_s = int(asked.split("since=")[1].split("s&")[0])
        assert 10 * MINUTE_NS <= since_s * 1e9 < 6 * HOUR_NS
    finally:
        page.close()
        relay.stop()
    assert not errors, errors
