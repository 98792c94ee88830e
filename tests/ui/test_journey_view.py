"""The page's Journeys tab and the Stage view's hop row: the shipped two-DCU configs (journey-dcu1 sends
RTP to journey-dcu2), both real ``dcuscope run --probes --relay`` processes; each frame's bar spans both
DCUs on the relay's clock, its hop hatched between them, as ``/api/journeys`` gives it."""

from __future__ import annotations

import pytest

from tests.relay.helpers import get_json, wait_for
from tests.ui.helpers import ROOT, RelayThread, pipeline_nodes, screenshot_with_address

pytestmark = pytest.mark.long

SHOTS = ROOT / "build" / "screenshots"  # git-ignored; docs/journeys.png is a copy chosen by hand
CONFIGS = ("configs/journey-dcu2.yaml", "configs/journey-dcu1.yaml")  # the receiver listens first


@pytest.fixture(scope="module")
def page(browser, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("journeys-page")
    relay = RelayThread(tmp / "relay.db")
    nodes = pipeline_nodes(relay.url, tmp, ["DCU-2", "DCU-1"], configs=CONFIGS, duration=25)
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(relay.url + "/")
        yield relay, page
        assert not errors, errors
    finally:
        page.close()
        nodes.stop()
        relay.stop()


def test_each_frames_bar_spans_both_dcus_with_its_hop_between(page):
    relay, page = page
    page.click('.tab[data-tab="journeys"]')
    last = wait_for(lambda: (d := page.evaluate("window.dcuscope.debug()")["journeys"])["journeys"] >= 40 and d,
                    90, 0.5, "40 journeys drawn in the Journeys tab")
    wait_for(lambda: page.locator("#overview-count").text_content().startswith("2 of 2"), 30, 0.5, "both DCUs listed")
    assert last["hops"] == 1 and last["message"] == ""
    bars = page.locator("#journeys-chart g.journey")
    assert bars.count() == last["journeys"]
    first = bars.first
    assert first.get_attribute("data-nodes") == "DCU-1 → DCU-2"
    parts = first.locator("rect.part")
    assert [parts.nth(i).get_attribute("data-name") for i in range(3)] == ["DCU-1", "net DCU-1 → DCU-2", "DCU-2"]
    assert "hop net DCU-1 → DCU-2:" in parts.nth(1).locator("title").text_content()
    # One bar, both DCUs: each segment starts where the one before ends, from the frame's first
    # origin on DCU-1 to its end on DCU-2.
    spans = [(int(parts.nth(i).get_attribute("data-at-ns")), int(parts.nth(i).get_attribute("data-ns")))
             for i in range(3)]
    assert spans[0][0] == 0 and all(a[0] + a[1] == b[0] for a, b in zip(spans, spans[1:]))
    assert spans[2][0] + spans[2][1] == int(first.get_attribute("data-total-ns"))
    xs = [float(parts.nth(i).get_attribute("x")) for i in (0, 2)]
    assert xs[0] < xs[1]
    hop = get_json(f"{relay.url}/api/journeys")["hops"]["net DCU-1 → DCU-2"]
    assert f"{hop['lost']} lost" in page.locator("#journeys-hops").text_content()
    assert page.locator("#journeys-legend").text_content() == "on DCU-1on DCU-2a hop between two DCUs"
    SHOTS.mkdir(parents=True, exist_ok=True)
    screenshot_with_address(page, SHOTS / "journeys.png")


def test_the_stage_view_has_a_row_of_hops_after_the_dcus(page):
    relay, page = page
    page.click('.tab[data-tab="stage"]')
    hops = "⇄ hops"

    def drawn():
        d = page.evaluate("window.dcuscope.debug()")["stage"]
        return d if d["bars"].get(hops, {}).get("net DCU-1 → DCU-2", 0) > 0 else None

    d = wait_for(drawn, 60, 0.5, "hop bars in the Stage view")
    rows = [r for r in d["rows"] if r["source"] is None]
    assert [r["node"] for r in rows][-1] == hops and rows[-1]["lanes"] == ["net DCU-1 → DCU-2"]
    assert {r["node"] for r in rows} >= {"DCU-1", "DCU-2"}
    SHOTS.mkdir(parents=True, exist_ok=True)
    screenshot_with_address(page, SHOTS / "stage-hops.png")
