"""The Nodes panel at a glance, in headless Chromium against a real relay fed by two simulated
nodes without PTP: one short clock state per node with its offset ± uncertainty, the relay's
reason in full only in the clock's title and in the detail row a click opens."""

from __future__ import annotations

import pytest
from playwright.sync_api import TimeoutError as PlaywrightTimeout

from tests.relay.helpers import get_json, wait_for
from tests.ui.helpers import RelayThread, sim_nodes

NODES = ["DCU-1", "DCU-2"]
STATES = ("PTP locked", "PTP assumed", "estimate", "no estimate yet", "uncorrected", "ignored")
ROW_CHARS = 120
"""A node's row, closed: name, connection, clock state, offset, drift, PTP's state, counters, run."""


@pytest.fixture(scope="module")
def streaming(tmp_path_factory):
    """A relay, two nodes streaming to it with no ptp4l to read, both with a clock estimate."""
    tmp = tmp_path_factory.mktemp("nodespanel")
    relay = RelayThread(tmp / "relay.db")
    # 4 minutes of frames: the nodes outlive the module even on a loaded machine (they are stopped after it)
    feeder = sim_nodes(relay.url, tmp, NODES, frames=7200, sources=2, fps=30, paced=True,
                       offsets_ns=[0, 3_000_000], ptp_socket=tmp / "no-ptp4l-here")
    try:
        wait_for(lambda: len(n := get_json(f"{relay.url}/api/nodes")) == 2
                 and all(x["clock"]["applied"] == "estimate" for x in n), 30, 0.2, "both nodes' clock estimates")
        yield relay
    finally:
        feeder.stop()
        relay.stop()


@pytest.fixture
def page(browser, streaming):
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(streaming.url + "/")
    for node in NODES:
        try:
            page.wait_for_function(f"() => document.querySelector('#nodes-body tr[data-node=\"{node}\"] .clock-state')"
                                   "?.textContent === 'estimate'", timeout=40_000)
        except PlaywrightTimeout:
            rows = page.evaluate("() => [...document.querySelectorAll('#nodes-body tr')].map((r) => r.innerText)")
            clocks = {n["node"]: n["clock"] for n in get_json(f"{streaming.url}/api/nodes")}
            raise AssertionError(f"{node}'s row never said 'estimate' in 40 s: rows {rows}; the API: {clocks}") from None
    yield page
    page.close()
    assert not errors, errors


def test_each_node_shows_one_short_clock_state_and_no_reason(streaming, page):
    # PTP's state comes with a clock report: on a loaded machine the first may precede the
    # node's first read of ptp4l ("not read yet").
    nodes = wait_for(lambda: (ns := {n["node"]: n for n in get_json(f"{streaming.url}/api/nodes")}) and all(
        "no-ptp4l-here" in ns[node]["ptp"].get("reason", "") for node in NODES) and ns, 20, what="PTP read on every node")
    for node in NODES:
        assert nodes[node]["ptp"]["state"] == "unavailable" and "no-ptp4l-here" in nodes[node]["ptp"]["reason"]
        # The panel refreshes once a second: the page may still show the clock before that read.
        page.wait_for_function("([n, why]) => (document.querySelector(`#nodes-body tr[data-node=\"${n}\"] .clock-cell`)"
                               "?.getAttribute('title') || '').includes(why)", arg=[node, nodes[node]["clock"]["why"]],
                               timeout=10_000)
        row = page.locator(f'#nodes-body tr[data-node="{node}"]')
        state = row.locator(".clock-state").inner_text()
        assert state in STATES and len(state) <= 16, state
        assert row.locator(".clock-offset").inner_text().count("±") == 1
        assert row.locator(".ptp-state").inner_text() == "unavailable"
        text = row.inner_text()
        assert len(text) <= ROW_CHARS, text
        # The reason is in the clock's title (hover), not in the row.
        assert "not trusted" not in text and "ptp4l" not in text, text
        title = row.locator(".clock-cell").get_attribute("title")
        assert nodes[node]["clock"]["why"] in title and "docs/clocks.md" in title
    # Nothing of the reason repeats down the panel while no detail row is open.
    panel = page.locator("#nodes-panel").inner_text()
    assert "no-ptp4l-here" not in panel and "PTP not trusted" not in panel
    assert page.locator("#nodes-body tr.node-detail").count() == 0


def test_a_click_opens_the_reason_in_full_and_it_stays_open(streaming, page):
    page.click('#nodes-body tr[data-node="DCU-2"]')
    detail = page.locator('#nodes-body tr[data-detail="DCU-2"]')
    detail.wait_for(timeout=5_000)
    assert page.locator("#nodes-body tr.node-detail").count() == 1  # DCU-1's stays closed
    node = next(n for n in get_json(f"{streaming.url}/api/nodes") if n["node"] == "DCU-2")
    why = detail.locator(".clock-why").inner_text()
    assert why == node["clock"]["why"] and why.startswith("PTP not trusted: PTP unavailable (no ptp4l socket at ")
    assert "unavailable" in detail.locator(".ptp-cell").inner_text()
    sysclock = detail.locator(".sysclock").inner_text()
    assert sysclock and sysclock != "not reported"
    assert "docs/clocks.md" in detail.locator(".clock-howto").inner_text()
    # The reason appears once in the detail row, not once per line of it.
    assert detail.inner_text().count("no ptp4l socket") == 1
    # The panel refreshes every second (counters): the row stays open and the page stays as it was.
    events = page.locator('#nodes-body tr[data-node="DCU-2"] td').nth(6).inner_text()
    page.wait_for_function("(e) => document.querySelectorAll('#nodes-body tr[data-node=\"DCU-2\"] td')[6].textContent !== e",
                           arg=events, timeout=10_000)
    assert detail.count() == 1 and page.locator('#nodes-body tr[data-node="DCU-2"]').get_attribute("aria-expanded") == "true"
    page.click('#nodes-body tr[data-node="DCU-2"]')
    page.wait_for_selector('#nodes-body tr[data-detail="DCU-2"]', state="detached", timeout=5_000)


def test_a_click_that_spans_a_refresh_still_opens_the_row(streaming, page):
    """The panel is rebuilt every second (its counters), and the browser fires no click once the
    element pressed left the page: a press inside the panel holds it until the press ends."""
    events = '#nodes-body tr[data-node="DCU-1"] td:nth-child(7)'
    at = page.evaluate("(sel) => { const r = document.querySelector(sel).getBoundingClientRect(); "
                       "return [r.x + r.width / 2, r.y + r.height / 2]; }", events)
    page.mouse.move(*at)
    page.mouse.down()
    # Marked once pressed (the row may be rebuilt until then): a rebuild from here on would drop the mark.
    shown = page.evaluate("(sel) => { const td = document.querySelector(sel); td.dataset.pressed = 'here'; "
                          "return td.textContent; }", events)
    try:
        # Pressed until the relay counted other events than the row shows, and the page had 2 s to draw them.
        counted = wait_for(lambda: (n := f"{next(x for x in get_json(f'{streaming.url}/api/nodes') if x['node'] == 'DCU-1')['events']:,}")
                           != shown and n, 20, 0.2, "DCU-1's events counted on")
        page.wait_for_timeout(2000)
        held = page.locator("#nodes-body [data-pressed=here]").count() == 1 and page.locator(events).inner_text() == shown
    finally:
        page.mouse.up()
    assert held, f"the row was rebuilt during the press ({shown} events shown, the relay counted {counted})"
    page.locator('#nodes-body tr[data-detail="DCU-1"]').wait_for(timeout=5_000)
    page.wait_for_function("(e) => document.querySelectorAll('#nodes-body tr[data-node=\"DCU-1\"] td')[6].textContent !== e",
                           arg=shown, timeout=5_000)  # drawn once the press ended


YOUNG_PAGE = """
window.__frames = 0;
window.__panelsAt = null;
const raf = window.requestAnimationFrame.bind(window);
// A young clock, the same on every machine: frame k at k x 16.7 ms after the page's start.
window.requestAnimationFrame = (cb) => raf(() => { window.__frames += 1; cb(window.__frames * 1000 / 60); });
// Watched from the start (the first frame may come before DOMContentLoaded's listeners run): a
// change inside either panel once frames run is the page drawing it (the parser's come before).
new MutationObserver((changes) => {
  if (window.__panelsAt !== null || window.__frames === 0) return;
  const within = (n) => (n.nodeType === 1 ? n : n.parentElement)?.closest("#stats-body, #nodes-body");
  if (changes.some((c) => within(c.target))) {
    window.__panelsAt = window.__frames;
  }
}).observe(document, {childList: true, subtree: true, characterData: true});
"""


def test_the_panels_are_drawn_from_the_first_frame_of_a_page(browser, streaming):
    """requestAnimationFrame's clock starts at 0 as the page loads: panels last drawn "at 0" were
    first drawn only once that clock passed their refresh interval (frame 31 at 60 fps)."""
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    try:
        page.add_init_script(YOUNG_PAGE)
        page.goto(streaming.url + "/")
        try:
            page.wait_for_function("window.__panelsAt !== null", timeout=20_000)
        except PlaywrightTimeout:
            state = page.evaluate("({frames: window.__frames, app: window.dcuscope !== undefined})")
            raise AssertionError(f"no panel drawn in 20 s: {state}") from None
        assert page.evaluate("window.__panelsAt") == 1
        for node in NODES:  # and refreshed after, as data comes
            page.wait_for_selector(f'#nodes-body tr[data-node="{node}"]', timeout=20_000)
    finally:
        page.close()
