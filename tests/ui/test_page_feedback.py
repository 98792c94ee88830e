"""What the page tells its user, and how it copes, in headless Chromium against a real relay.

Bad limits are refused inline (an empty box clears the limit), tooltips stay inside the viewport, a stored session says that
its statistics have no rolling window, the favicon is served, a run that ended shows no frame
rate, and a relay that restarts on its port is reported as unreachable (not as a transport
error) and then followed again.
"""

from __future__ import annotations

import signal
import urllib.request

import pytest

from dcuscope.demo import status_lines
from tests.relay.helpers import get_json, wait_for
from tests.ui.helpers import KEEP_ENDED, RelayThread, sim_nodes, source_fps

pytestmark = pytest.mark.long  # its tests share a module fixture: one group of 30 s or more, started first

LONG_NODE = "DCU-" + "north-wing-loading-dock-camera-rack-" * 3 + "7"
RAW_ERRORS = ("xhr", "poll error", "websocket error", "backfill", "no node named", "Failed to fetch")


def debug(page) -> dict:
    return page.evaluate("window.dcuscope.debug()")


def open_page(browser, url: str, viewport: dict | None = None, polling: bool = False):
    """A page on ``url`` (``polling``: without the Socket.IO client) and the page and console errors it reports."""
    page = browser.new_page(viewport=viewport or {"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    if polling:
        page.route("**/vendor/socket.io.min.js", lambda route: route.abort())
    page.goto(url + "/")
    page.wait_for_function("window.dcuscope !== undefined", timeout=15000)
    return page, errors


@pytest.fixture(scope="module")
def ended(tmp_path_factory):
    """A relay and a node with a long name that streamed 200 frames of 3 sources and ended."""
    tmp = tmp_path_factory.mktemp("feedback")
    relay = RelayThread(tmp / "relay.db", limits=KEEP_ENDED)
    feeder = sim_nodes(relay.url, tmp, [LONG_NODE], frames=200, sources=3, fps=30, paced=False)
    try:
        feeder.wait(120)
        wait_for(lambda: any(n["node"] == LONG_NODE and n["frames"]["shown"] == 600
                             for n in get_json(f"{relay.url}/api/nodes")), 30, 0.2, "every frame on the relay")
        yield relay
    finally:
        feeder.stop()
        relay.stop()


def test_set_limit_refuses_zero_and_negative_saying_why_and_an_empty_box_clears_it(ended, browser):
    page, errors = open_page(browser, ended.url)
    try:
        page.click(".tab[data-tab=frame]")
        counts = page.locator(f'.frame-panel[data-node="{LONG_NODE}"] .frame-head')
        # No limit by default (the relay has no --frame-limit): nothing judged, and the line says how to set one.
        wait_for(lambda: "no limit set" in counts.inner_text(), 15, 0.2, "the counts without a limit")
        d = debug(page)
        assert d["limit"] is None and d["frame"]["nodes"][LONG_NODE]["limit"] is None
        p99 = d["stats"][LONG_NODE]["frame"]["p99_ms"]
        assert f"no limit set: type one above (its p99: " in counts.inner_text() and p99 > 0
        for typed, before, box in (("0", "none", ""), ("-3", "none", ""), ("12.5", None, "12.5"), ("0", "12.5 ms", "12.5")):
            page.fill("#limit-input", typed)
            page.click("#set-limit")
            if before is None:  # taken
                wait_for(lambda: debug(page)["frame"]["limit"] == 12.5, 5, 0.1, "the new limit drawn")
                assert page.locator("#limit-msg").is_hidden() and page.input_value("#limit-input") == "12.5"
                continue
            page.wait_for_selector("#limit-msg", state="visible", timeout=5000)
            msg = page.locator("#limit-msg").inner_text()
            assert f"“{typed}” is not a delay above 0 ms" in msg and f"still {before}" in msg, msg
            # The box shows the limit in force, not what was refused.
            assert page.input_value("#limit-input") == box
        assert "shown over 12.5 ms" in counts.inner_text()
        page.fill("#limit-input", "")
        page.press("#limit-input", "Enter")
        wait_for(lambda: debug(page)["frame"]["nodes"][LONG_NODE]["limit"] is None, 5, 0.1, "the limit cleared")
        assert page.locator("#limit-msg").is_hidden() and "no limit set" in counts.inner_text()
        assert not errors, errors
    finally:
        page.close()


def test_frame_tooltip_stays_in_the_viewport_with_its_text_in_its_box(ended, browser):
    page, errors = open_page(browser, ended.url, {"width": 640, "height": 560})
    try:
        page.click(".tab[data-tab=frame]")
        wait_for(lambda: debug(page)["frame"]["nodes"].get(LONG_NODE, {}).get("shown", 0) > 0, 30, 0.2,
                 "frame bars")
        canvas = page.locator(f'.frame-panel[data-node="{LONG_NODE}"] canvas')
        canvas.scroll_into_view_if_needed()
        box = canvas.bounding_box()
        # Bars span the plot's full height (75 frames, 4 px each); the points are near the viewport's right and bottom.
        for x, y in ((box["x"] + box["width"] - 20, box["y"] + 60),
                     (box["x"] + box["width"] - 20, min(box["y"] + 300, 560 - 4)),
                     (box["x"] + 100, min(box["y"] + 300, 560 - 4))):
            page.mouse.move(x, y)
            tip = wait_for(lambda: debug(page)["tooltip"], 5, 0.1, f"the tooltip at {x}, {y}")
            assert LONG_NODE in tip
            r = page.evaluate("""() => { const t = document.querySelector('#tooltip'), b = t.getBoundingClientRect();
                return {left: b.left, right: b.right, top: b.top, bottom: b.bottom,
                        vw: document.documentElement.clientWidth, vh: document.documentElement.clientHeight,
                        sw: t.scrollWidth, cw: t.clientWidth, sh: t.scrollHeight, ch: t.clientHeight}; }""")
            assert 0 <= r["left"] and r["right"] <= r["vw"] and 0 <= r["top"] and r["bottom"] <= r["vh"], r
            assert r["sw"] <= r["cw"] and r["sh"] <= r["ch"], r
            page.mouse.move(2, 2)
            wait_for(lambda: debug(page)["tooltip"] is None, 5, 0.1, "the tooltip to go")
        assert not errors, errors
    finally:
        page.close()


def test_stored_session_disables_the_rolling_window_saying_why(ended, browser):
    page, errors = open_page(browser, ended.url)
    try:
        assert page.is_enabled("#stats-window") and page.locator("#stats-window-note").is_hidden()
        sid = get_json(f"{ended.url}/api/sessions")[0]["session"]
        page.locator("#session-select").focus()
        page.wait_for_selector(f'#session-select option[value="{sid}"]', state="attached", timeout=15000)
        page.select_option("#session-select", str(sid))
        wait_for(lambda: (lambda d: d["mode"] == "session" and d["loaded"])(debug(page)), 30, 0.2, "the session")
        assert page.is_disabled("#stats-window")
        assert "live data only" in page.locator("#stats-window-note").inner_text()
        page.select_option("#session-select", "live")
        wait_for(lambda: debug(page)["mode"] == "live", 5, 0.1, "back to live")
        assert page.is_enabled("#stats-window") and page.locator("#stats-window-note").is_hidden()
        assert not errors, errors
    finally:
        page.close()


def test_favicon_is_served_and_loading_the_page_logs_no_error(ended, browser):
    page, errors = open_page(browser, ended.url)
    try:
        page.wait_for_function("document.querySelector('#conn').textContent === 'live'", timeout=15000)
        href = page.evaluate("document.querySelector('link[rel=icon]').href")
        for url in (href, f"{ended.url}/favicon.ico"):
            with urllib.request.urlopen(url, timeout=10) as r:
                assert r.status == 200 and r.headers["Content-Type"].startswith("image/svg+xml")
                assert b"<svg" in r.read()
        assert not errors, errors
    finally:
        page.close()


def test_an_ended_run_shows_no_fps_in_its_row_the_api_metrics_and_the_demo_line(ended, browser):
    """It has no rate: its row says "ended" where the fps was, /api/overview gives fps null, /metrics
    0 frames/s for its sources, and the demo's status line says it ended. (A run gone silent
    without ending reads 0 once its frames left the window: tests/ui/test_overview.py.)"""
    page, errors = open_page(browser, ended.url)
    try:
        cell = page.locator(f'#overview tbody tr[data-node="{LONG_NODE}"] td.ov-fps')
        wait_for(lambda: cell.count() == 1 and cell.inner_text() != "", 15, 0.2, "its row")
        row = next(r for r in get_json(f"{ended.url}/api/overview")["rows"] if r["node"] == LONG_NODE)
        assert (row["state"], row["fps"]) == ("ended", None), row
        assert cell.inner_text() == "ended"
        assert source_fps(ended.url, LONG_NODE) == {"0": 0.0, "1": 0.0, "2": 0.0}
        assert status_lines(ended.url) == [f"{LONG_NODE}: ended (600 frames)"]
        assert not errors, errors
    finally:
        page.close()


@pytest.mark.parametrize("polling", [False, True], ids=["socketio", "polling"])
def test_relay_restart_reads_unreachable_then_the_live_view_resumes(browser, tmp_path, polling):
    relay = RelayThread(tmp_path / "relay.db")
    port = relay.port
    # Paced: 30 frames/s of one source for up to 60 s, through the restart.
    feeder = sim_nodes(relay.url, tmp_path, ["DCU-1"], frames=1800, sources=1, fps=30, paced=True)
    node = feeder.procs[0]
    page = None
    try:
        page, errors = open_page(browser, relay.url, polling=polling)
        live = "polling the HTTP API (the Socket.IO client (vendor/socket.io.min.js) is not installed)" if polling else "live"
        # Every status the page shows, in order (setting the same text again counts too).
        page.evaluate("""() => { window.connTexts = [];
            new MutationObserver(() => window.connTexts.push(document.querySelector('#conn').textContent))
                .observe(document.querySelector('#conn'), {childList: true, characterData: true, subtree: true}); }""")
        wait_for(lambda: debug(page)["stores"].get("DCU-1", {}).get("received", 0) > 30, 60, 0.2, "live frames")
        # The node is held still, so that the page is back before the node: the restarted relay
        # does not know DCU-1 yet when the page reconnects.
        node.send_signal(signal.SIGSTOP)
        relay.stop()
        # The hang-up, then at least one failed attempt to reconnect (Socket.IO's "xhr poll error",
        # the API's "Failed to fetch").
        page.wait_for_function("window.connTexts.filter((t) => t === 'relay unreachable, retrying').length >= 2",
                               timeout=30000)
        before = debug(page)["stores"]["DCU-1"]["received"]
        relay = RelayThread(tmp_path / "relay.db", port=port)
        page.wait_for_function("(live) => document.querySelector('#conn').textContent === live", arg=live,
                               timeout=30000)
        node.send_signal(signal.SIGCONT)
        # The node reconnects too: its frames reach the page again and the stage view draws them.
        d = wait_for(lambda: (lambda d: d if d["stores"]["DCU-1"]["received"] > before + 60
                              and sum(d["stage"]["bars"].get("DCU-1", {}).values()) > 0 else None)(debug(page)),
                     60, 0.3, "frames after the restart")
        assert not d["paused"] and d["mode"] == "live"
        texts = page.evaluate("window.connTexts")
        assert not [t for t in texts if any(raw in t for raw in RAW_ERRORS)], texts
        assert set(texts) == {"relay unreachable, retrying", live}, texts
        assert page.locator("#conn").inner_text() == live and page.locator("#banner").is_hidden()
        # Chromium logs the refused connections themselves as console errors; the page raised none.
        assert not [e for e in errors if "ERR_CONNECTION_REFUSED" not in e and "Failed to load" not in e], errors
    finally:
        if page is not None:
            page.close()
        if node.poll() is None:
            node.send_signal(signal.SIGCONT)
        feeder.stop()
        relay.stop()
