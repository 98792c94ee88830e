"""The page at a laptop's width, in headless Chromium against a real relay fed by 16 simulated DCUs.

The header fits from 1024 to 1920 px (every control inside the viewport, every label on one line,
the data selector as wide as its longest entry, not the header); with no DCU opened the overview
shows all 16 rows at 1280x800 without scrolling and the views below collapse to a line each; the
keys (``/``, up, down, Enter, Escape) reach, open and close a DCU; the overview's height with DCUs
opened follows its grip and is remembered across a reload. The screenshots at 1280x800 (none
opened, one opened) are written to build/screenshots. The tests run in order on one relay: the
last stops it and checks the header still fits at 1024 px with the longest status it then shows.
"""

from __future__ import annotations

import threading

import pytest

from tests.relay.helpers import wait_for
from tests.ui.helpers import streaming_fleet
from tests.ui.test_browser import SHOTS

NODES = [f"DCU-{k:02d}" for k in range(1, 17)]
WIDTHS = (1024, 1280, 1920)
DEFAULT_PX = 250  # style.css: the overview's height with DCUs opened, until its grip is used

# Per element of the header: its box, and the line tops of its text (a label on one line has one).
HEADER_JS = """() => [...document.querySelectorAll('.top > *')].filter((el) => el.getClientRects().length)
  .map((el) => {
    const r = el.getBoundingClientRect();
    const range = document.createRange();
    range.selectNodeContents(el);
    const tops = new Set([...range.getClientRects()].filter((q) => q.width > 0 && q.height > 0)
      .map((q) => Math.round(q.top + q.height / 2)));
    return {el: el.id || el.className || el.tagName, left: r.left, right: r.right, top: r.top, bottom: r.bottom,
            lines: tops.size, text: el.innerText};
  })"""

ROWS_JS = """() => {
  const wrap = document.querySelector('.overview-wrap').getBoundingClientRect();
  const rows = [...document.querySelectorAll('#overview tbody tr:not([hidden])')].map((tr) => {
    const r = tr.getBoundingClientRect();
    return {node: tr.dataset.node, top: r.top, bottom: r.bottom};
  });
  const box = (sel) => document.querySelector(sel).getBoundingClientRect().height;
  return {rows, wrap: {top: wrap.top, bottom: wrap.bottom, height: wrap.height},
          scroller: document.querySelector('.overview-wrap').scrollHeight - document.querySelector('.overview-wrap').clientHeight,
          page: document.documentElement.scrollHeight - innerHeight, height: innerHeight,
          fleetOnly: document.body.classList.contains('fleet-only'),
          panels: {stage: box('#stage-view'), nodes: box('#nodes-panel'), stats: box('#stats-panel')}};
}"""


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """A relay and 16 simulated DCUs streaming to it (one camera each at 2 fps, paced, up to 5 minutes)."""
    with streaming_fleet(tmp_path_factory.mktemp("ui-layout"), NODES, frames=600, sources=1, fps=2.0,
                         within_s=90) as fleet:
        yield fleet


@pytest.fixture(scope="module")
def page(fleet, browser):
    """One page for the module's tests, in order (each leaves it at 1280x800 with no DCU opened), and
    the errors it raised."""
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(fleet[0].url + "/")
    loaded(page)
    try:
        yield page, errors
    finally:
        page.close()


def loaded(page) -> None:
    page.wait_for_function(f"window.dcuscope && window.dcuscope.debug().overview.total === {len(NODES)}",
                           timeout=30000)


def header_fits(page, width: int) -> dict[str, dict]:
    """Assert every control of the header lies inside the viewport, its label on one line; returns them."""
    boxes = {b["el"]: b for b in page.evaluate(HEADER_JS)}
    assert {"pause", "zoom-reset", "clock-mode", "relay-clock", "conn", "control data-control"} <= set(boxes), boxes
    for b in boxes.values():
        if b["el"] == "spacer":
            continue
        assert 0 <= b["left"] and b["right"] <= width and 0 <= b["top"] and b["bottom"] <= 60, (width, b)
        assert b["lines"] <= 1, f"at {width} px {b['el']} breaks its label {b['text']!r} over {b['lines']} lines"
    assert page.evaluate("document.documentElement.scrollWidth") <= width
    return boxes


def test_the_header_fits_from_1024_px_with_the_data_selector_as_wide_as_its_entries(page):
    page, errors = page
    # The stored session of the 16 DCUs: its entry names two and counts the rest, all of them in its tooltip.
    option = page.wait_for_selector('#session-select option:not([value="live"])', state="attached", timeout=15000)
    assert option.inner_text().endswith("DCU-01, DCU-02 +14"), option.inner_text()
    assert option.get_attribute("title") == ", ".join(NODES)
    widths = {}
    for width in WIDTHS:
        page.set_viewport_size({"width": width, "height": 800})
        boxes = header_fits(page, width)
        select = page.evaluate("""() => { const s = document.querySelector('#session-select');
            const probe = document.createElement('span');
            probe.style.cssText = 'position:absolute;visibility:hidden;white-space:nowrap;font:' + getComputedStyle(s).font;
            document.body.append(probe);
            const longest = Math.max(...[...s.options].map((o) => { probe.textContent = o.text; return probe.offsetWidth; }));
            probe.remove();
            return {width: s.getBoundingClientRect().width, longest, max: parseFloat(getComputedStyle(s).maxWidth)}; }""")
        widths[width] = select["width"]
        # As wide as its longest entry (and its arrow), up to its maximum: not stretched by the header.
        assert select["width"] <= select["max"] + 1, select
        assert select["width"] >= min(select["longest"], select["max"] - 30), select
        # Below 1280 px the short labels; from 1280 px the long ones.
        want = ("Reset", "Clock: corrected") if width < 1280 else ("Reset view", "Clock: corrected")
        assert (boxes["zoom-reset"]["text"], boxes["clock-mode"]["text"]) == want, boxes
    assert widths[1920] == widths[1280], widths  # wider screens give the selector nothing more
    page.set_viewport_size({"width": 1280, "height": 800})
    assert not errors, errors


def test_16_dcus_with_none_opened_all_show_at_1280x800_and_the_keys_open_one(page):
    page, errors = page
    layout = wait_for(lambda: (lambda d: d if d["fleetOnly"] and len(d["rows"]) == len(NODES) else None)(
        page.evaluate(ROWS_JS)), 10, 0.2, "the overview taking the screen")
    # Every row inside the overview's box and the viewport, nothing to scroll, in the box or the page.
    assert layout["scroller"] <= 0 and layout["page"] <= 0, layout
    for r in layout["rows"]:
        assert layout["wrap"]["top"] <= r["top"] and r["bottom"] <= min(layout["wrap"]["bottom"], 800) + 0.5, r
    # The stage view and the two panels are one line each (their padding and border around it).
    assert all(h <= 42 for h in layout["panels"].values()), layout["panels"]
    assert page.locator("#stage-view .view-empty").inner_text().startswith("No DCU opened: click one of the 16")
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / "overview-none-opened.png"))

    focused = "() => document.activeElement.id || document.activeElement.dataset.node || document.activeElement.tagName"
    page.keyboard.press("/")
    assert page.evaluate(focused) == "overview-filter"
    page.keyboard.press("ArrowDown")
    first = page.evaluate(focused)
    page.keyboard.press("ArrowDown")
    page.keyboard.press("ArrowDown")
    page.keyboard.press("ArrowUp")
    second = page.evaluate(focused)
    # The order held still under the keys: the first row and the second.
    rows_now = page.evaluate("() => [...document.querySelectorAll('#overview tbody tr')].map((tr) => tr.dataset.node)")
    assert rows_now.index(first) == 0 and rows_now.index(second) == 1, (first, second, rows_now)
    page.keyboard.press("Enter")
    wait_for(lambda: page.evaluate("window.dcuscope.debug().opened") == [second], 10, 0.1, f"{second} opened")
    # The DCU's views are drawn, the overview back to its height, and the row keeps the keys' focus.
    wait_for(lambda: page.evaluate("window.dcuscope.debug().stage.rows.length") > 0, 20, 0.2, "its stage view")
    layout = page.evaluate(ROWS_JS)
    assert not layout["fleetOnly"] and layout["wrap"]["height"] <= DEFAULT_PX + 0.5, layout["wrap"]
    assert layout["panels"]["stage"] > 150, layout["panels"]
    assert page.evaluate(focused) == second
    assert page.locator(f'#overview tr[data-node="{second}"]').get_attribute("aria-expanded") == "true"
    page.mouse.move(640, 780)  # off the table: the screenshot shows the row as the keys left it
    page.wait_for_timeout(1200)
    page.screenshot(path=str(SHOTS / "overview-one-opened.png"))
    page.keyboard.press("Enter")
    wait_for(lambda: page.evaluate("window.dcuscope.debug().opened") == [], 10, 0.1, f"{second} closed")
    wait_for(lambda: page.evaluate(ROWS_JS)["fleetOnly"], 10, 0.1, "the overview taking the screen again")
    # Escape: back to the filter; "/" typed there is a character, not the shortcut.
    page.keyboard.press("Escape")
    assert page.evaluate(focused) == "overview-filter"
    page.keyboard.type("DCU-1/")
    assert page.input_value("#overview-filter") == "DCU-1/"
    page.fill("#overview-filter", "")
    assert not errors, errors


def test_the_overview_height_follows_its_grip_and_a_reload_keeps_it(page):
    page, errors = page
    page.click(f'#overview tr[data-node="{NODES[0]}"]')
    height = "() => document.querySelector('.overview-wrap').getBoundingClientRect().height"
    wait_for(lambda: abs(page.evaluate(height) - DEFAULT_PX) < 1, 10, 0.1, "the default height")
    grip = page.locator("#overview-grip").bounding_box()
    x, y = grip["x"] + grip["width"] / 2, grip["y"] + grip["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x, y + 60, steps=5)
    page.mouse.move(x, y + 100, steps=5)
    page.mouse.up()
    chosen = page.evaluate(height)
    assert abs(chosen - (DEFAULT_PX + 100)) <= 1, chosen
    page.reload()  # the address says which DCU is open: the same page again
    loaded(page)
    assert page.evaluate("window.dcuscope.debug().opened") == [NODES[0]]
    assert abs(page.evaluate(height) - chosen) <= 1
    # The keys on the grip: a row's height a press; a double-click: the default, forgotten.
    page.focus("#overview-grip")
    page.keyboard.press("ArrowUp")
    assert abs(page.evaluate(height) - (chosen - 24)) <= 1
    page.dblclick("#overview-grip")
    assert abs(page.evaluate(height) - DEFAULT_PX) <= 1
    assert page.evaluate("localStorage.getItem('dcuscope.overviewHeight')") is None
    page.click("#overview-close")
    assert not errors, errors


def test_the_header_still_fits_at_1024_px_paused_with_the_relay_down(fleet, page):
    page, errors = page
    relay, feeder = fleet
    page.set_viewport_size({"width": 1024, "height": 800})
    page.click("#pause")
    feeder.stop()
    # Stopped on a thread of its own: the page is watched meanwhile (a relay may take a while to close).
    stopping = threading.Thread(target=relay.stop, daemon=True)
    stopping.start()
    try:
        wait_for(lambda: "unreachable" in page.locator("#conn").inner_text(), 30, 0.2, "the page telling the relay is down")
        boxes = header_fits(page, 1024)
        assert boxes["pause"]["text"] == "Resume"
        assert page.locator("#conn").get_attribute("title") == boxes["conn"]["text"]  # in full where it is cut
        assert not errors, errors
    finally:
        stopping.join(30)
