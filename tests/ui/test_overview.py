"""The fleet overview in headless Chromium against a real relay fed by six simulated DCUs.

Six DCUs are more than the page opens by itself: the overview lists them all, worst first, and
nothing else is drawn or pushed until a row is clicked. The tests of this module run in order on
one relay: the rows and their fields, the order after a DCU is killed, the filter, opening and
closing a DCU (the relay then pushes that DCU's frames only, and closing it drops them), ?open=
in the address, the same without Socket.IO (polling the HTTP API), and last the relay stopping
(rows shown stale, then gone).
"""

from __future__ import annotations

import json
import re
import signal
import threading
import time

import pytest

from tests.relay.helpers import get_json, wait_for
from tests.ui.helpers import source_fps, streaming_fleet

pytestmark = pytest.mark.long  # its tests share a module fixture: one group of 30 s or more, started first

NODES = [f"DCU-{k}" for k in range(1, 7)]
KILLED = "DCU-5"
SOURCES, FPS = 2, 10.0


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """A relay and six simulated DCUs streaming to it (paced, for up to 5 minutes)."""
    with streaming_fleet(tmp_path_factory.mktemp("ui-overview"), NODES, frames=int(FPS * 300), sources=SOURCES,
                         fps=FPS, within_s=60) as fleet:
        yield fleet


class Traffic:
    """What the relay pushes to a page over its WebSocket: per event, the DCUs named."""

    def __init__(self, page) -> None:
        self.events: list[tuple[float, str, object]] = []
        page.on("websocket", lambda ws: ws.on("framereceived", self.received))

    def received(self, payload) -> None:
        # An event (42) or an event with binary attachments (45N-: the pushed frames), in /ui.
        if not isinstance(payload, str) or not re.match(r"4(2|5\d+-)/ui,", payload):
            return
        event, data = json.loads(payload[payload.index("["):])[:2]
        self.events.append((time.monotonic(), event, data))

    def nodes_in(self, since: float) -> dict[str, set[str]]:
        """The DCUs each kind of push named since ``since`` (monotonic time)."""
        out: dict[str, set[str]] = {"frames": set(), "stats": set(), "nodes": set(), "overview": set()}
        for t, event, data in self.events:
            if t < since:
                continue
            if event in ("frames", "stats"):
                out[event] |= set(data["nodes"])
            elif event == "nodes":
                out[event] |= {n["node"] for n in data}
            elif event == "overview":
                out[event] |= {r["node"] for r in data["rows"]}
        return out


def open_page(browser, url: str, path: str = "/"):
    page = browser.new_page(viewport={"width": 1400, "height": 950})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    traffic = Traffic(page)
    page.goto(url + path)
    page.wait_for_function("window.dcuscope !== undefined", timeout=30000)
    return page, errors, traffic


def debug(page) -> dict:
    return page.evaluate("window.dcuscope.debug()")


def stale_snapshot(page) -> dict:
    """The overview's rows, how many table rows are drawn stale, and DCU-1's cells, at one moment."""
    return page.evaluate("""() => ({
        rows: window.dcuscope.debug().overview.rows,
        drawnStale: document.querySelectorAll('#overview tbody tr.stale').length,
        dcu1: [...document.querySelectorAll('#overview tbody tr[data-node="DCU-1"] td')].map(td => td.innerText),
    })""")


def cells(page, node: str) -> list[str]:
    return page.locator(f'#overview tbody tr[data-node="{node}"] td').all_inner_texts()


def worst_first_key(row: dict):
    """The order the overview's tooltip states: down first, then alerts, utilization, p99, name."""
    return (not row["down"], -len(row["alerts"]), -row["util"], -row["p99"], row["node"])


@pytest.fixture(scope="module")
def page(fleet, browser):
    relay, _ = fleet
    page, errors, traffic = open_page(browser, relay.url)
    try:
        yield page, traffic
        assert not errors, errors
    finally:
        page.close()


def test_the_overview_lists_every_dcu_with_its_figures_and_opens_none(fleet, page):
    relay, _ = fleet
    page, traffic = page
    name = get_json(f"{relay.url}/api/overview")["relay"]
    # Figures once every node streams (a loaded machine starts the nodes late: their fps reads 0 until then).
    d = wait_for(lambda: (lambda d: d if d["overview"]["total"] == len(NODES) and all(
        c[2] != "–" and float(c[2]) >= 0.6 * SOURCES * FPS for c in (cells(page, n) for n in NODES)) else None)(debug(page)),
        60, 0.3, "six rows with figures")
    assert d["overview"]["count"] == "6 of 6 DCUs · 0 opened"
    api = {r["node"]: r for r in get_json(f"{relay.url}/api/overview")["rows"]}
    for node in NODES:
        dcu, held_by, fps, p99, neck, clock, drops, alerts = cells(page, node)
        assert dcu.endswith(node) and held_by == name == api[node]["relay"]
        assert 0.6 * SOURCES * FPS <= float(fps) <= 1.4 * SOURCES * FPS, fps
        assert re.fullmatch(r"[\d.]+ ms", p99), p99
        assert neck.split()[0] == api[node]["bottleneck"]["stage"]
        assert clock.split()[0] in ("estimate", "no", "PTP"), clock  # the nodes panel's words (panels.clockState)
        assert drops == "0"
        assert alerts == "–" or re.match(r"\d+ \S", alerts), alerts  # none, or their count and texts
    # More than four DCUs: the page opened none, subscribed to none, holds no frames, draws no row.
    assert d["opened"] == [] and not d["chosen"] and d["liveStores"] == [] and d["stage"]["rows"] == []
    sub = wait_for(lambda: (lambda s: s if s and s["ack"] else None)(debug(page)["subscription"]), 10, 0.1,
                   "the relay's answer to the subscription")
    assert sub == {"nodes": [], "max_frames": 25, "overview": True, "ack": {"ok": True}}
    assert "No DCU opened" in page.locator("#nodes-body").inner_text()
    since, drawn = time.monotonic(), debug(page)["draws"]
    page.wait_for_timeout(2500)
    # Nothing to draw: the views are drawn twice a second (their axis moves), not every animation frame.
    assert 1 <= debug(page)["draws"] - drawn <= 7
    seen = traffic.nodes_in(since)
    assert seen["frames"] == set() and seen["stats"] == set() and seen["nodes"] == set()
    assert seen["overview"] == set(NODES)


def test_worst_first_follows_the_data_a_disconnected_dcu_comes_first(fleet, page):
    _, feeder = fleet
    page, _ = page
    page.mouse.move(5, 5)  # the order holds still under the pointer
    feeder.procs[NODES.index(KILLED)].send_signal(signal.SIGKILL)

    last = []

    def killed_first():
        last[:] = rows = debug(page)["overview"]["rows"]
        return rows if rows and rows[0]["node"] == KILLED and "disconnected" in rows[0]["alerts"] else None

    try:
        rows = wait_for(killed_first, 45, 0.3, f"{KILLED} first, disconnected")
    except AssertionError as exc:
        raise AssertionError(f"{exc}: the page's rows {last}") from None
    # The table's order is the worst-first rule applied to what it shows.
    assert [r["node"] for r in rows] == [r["node"] for r in sorted(rows, key=worst_first_key)]
    assert page.locator("#overview tbody tr").first.get_attribute("data-node") == KILLED
    assert "disconnected" in cells(page, KILLED)[7]
    assert page.locator("#overview-order").get_attribute("title").startswith("Worst first: DCUs down")


def test_the_filter_keeps_rows_whose_dcu_relay_bottleneck_or_alerts_match(fleet, page):
    relay, _ = fleet
    page, _ = page
    overview = get_json(f"{relay.url}/api/overview")
    name = overview["relay"]
    stage = next(r["bottleneck"]["stage"] for r in overview["rows"] if r["bottleneck"])

    def matching(text: str) -> list[str]:
        """The rule, applied to the relay's rows now: every word in the DCU, relay, bottleneck or alerts."""
        rows = get_json(f"{relay.url}/api/overview")["rows"]
        hay = {r["node"]: "\n".join([r["node"], r["relay"], (r["bottleneck"] or {}).get("stage") or "", *r["alerts"]])
               for r in rows}
        return sorted(n for n, h in hay.items() if all(w in h.lower() for w in text.lower().split()))

    def shown(text: str, want: list[str] | None = None) -> list[str]:
        """The rows the page shows for ``text``, once they are ``want`` (default: what the rule gives
        on the relay's rows: a loaded machine may turn a DCU's bottleneck or alerts meanwhile)."""
        page.fill("#overview-filter", text)
        last = []

        def agree():
            rows = page.locator("#overview tbody tr:not([hidden])")
            last[:] = sorted(rows.evaluate_all("(rs) => rs.map((r) => r.dataset.node)"))
            return last == (want if want is not None else matching(text))

        try:
            wait_for(agree, 10, 0.2, f"the rows filtered by {text!r}")
        except AssertionError:
            pass  # the caller's assertion says what was shown
        return last

    assert shown("dcu-2") == ["DCU-2"]
    assert page.locator("#overview-count").inner_text() == "1 of 6 DCUs · 0 opened"
    assert shown(name) == NODES
    assert len(shown(stage.upper())) >= 1 and shown(stage.upper()) == matching(stage)
    assert shown("disconnected") == [KILLED]
    assert shown(f"{KILLED.lower()} disconn") == [KILLED]
    assert shown("nothing-matches-this", []) == []
    assert page.locator("#overview-count").inner_text() == "0 of 6 DCUs · 0 opened"
    assert shown("", NODES) == NODES


def click_row(page, node: str) -> None:
    """Click ``node``'s row as a user does: the pointer over the rows first, which holds their order
    still (a push may reorder them, worst first, between finding a row and the pointer reaching it)."""
    page.hover("#overview tbody tr[data-node] >> nth=0")
    page.click(f'#overview tbody tr[data-node="{node}"]')


def address(page) -> str:
    """The page's address as the page holds it now (``page.url`` follows it later, after an event
    from the browser: read right after a click, it may still be the one before)."""
    return page.evaluate("location.pathname + location.search")


def test_a_click_opens_one_dcu_and_the_relay_pushes_only_its_frames(fleet, page):
    page, traffic = page
    node = "DCU-3"
    click_row(page, node)
    assert address(page) == f"/?open={node}"
    d = wait_for(lambda: (lambda d: d if sum(d["stage"]["bars"].get(node, {}).values()) > 0 else None)(debug(page)),
                 30, 0.3, f"{node}'s bars")
    assert [r["node"] for r in d["stage"]["rows"]] == [node] and d["liveStores"] == [node]
    want = {"nodes": [node], "max_frames": 25, "overview": True, "ack": {"ok": True}}
    wait_for(lambda: debug(page)["subscription"] == want, 10, 0.1, "the relay's answer to the subscription")
    assert page.locator(f'#overview tbody tr[data-node="{node}"]').get_attribute("class").split().count("open") == 1
    wait_for(lambda: page.locator(f'#nodes-body tr.node-row[data-node="{node}"]').count() == 1, 10, 0.2, "its node row")
    since = time.monotonic()
    page.wait_for_timeout(2500)
    # At least 2.5 s, until its frames and every row came (a loaded machine is slower).
    seen = wait_for(lambda: (lambda s: s if s["frames"] and s["overview"] == set(NODES) else None)(traffic.nodes_in(since)),
                    30, 0.2, "its frames and the overview's rows pushed")
    assert seen["frames"] == {node}, seen  # pushed, and no other DCU's
    assert seen["stats"] <= {node} and seen["nodes"] <= {node} and seen["overview"] == set(NODES)
    d = debug(page)
    assert list(d["stores"]) == [node] and set(d["stats"]) <= {node} and [n["node"] for n in d["nodes"]] == [node]
    page.click(".tab[data-tab=frame]")
    page.wait_for_timeout(300)
    assert page.locator(".frame-panel").evaluate_all("(ps) => ps.map((p) => p.dataset.node)") == [node]
    page.click(".tab[data-tab=stage]")

    # Closed again: its frames are dropped and the relay stops pushing them.
    click_row(page, node)
    assert address(page) == "/?open="
    d = debug(page)
    assert d["liveStores"] == [] and d["stores"] == {} and d["stats"] == {} and d["nodes"] == []
    assert page.locator(".frame-panel").count() == 0
    page.wait_for_timeout(1000)  # pushes already under way
    since = time.monotonic()
    page.wait_for_timeout(2000)
    assert traffic.nodes_in(since)["frames"] == set()
    assert debug(page)["liveStores"] == []


def test_a_click_that_spans_a_push_still_opens_the_dcu(fleet, page):
    """A press lasts ~0.1 s and the rows' figures change every second. The browser fires no click
    once the element pressed left the page, so a cell rewritten under a press would lose its click:
    the overview holds its rows while a press is on them and draws them when it ends."""
    page, traffic = page
    node = "DCU-1"
    name = f'#overview tbody tr[data-node="{node}"] .ov-name'
    page.hover("#overview tbody tr[data-node] >> nth=0")  # the rows' order holds still from here
    at = page.evaluate("(sel) => { const r = document.querySelector(sel).getBoundingClientRect(); "
                       "return [r.x + r.width / 2, r.y + r.height / 2]; }", name)
    page.mouse.move(*at)
    page.mouse.down()
    since = time.monotonic()
    # Watched once pressed (the rows may change until then): any change to them from here on is counted.
    page.evaluate("""() => {
        window.__rowChanges = 0;
        window.__rowWatch = new MutationObserver((ms) => { window.__rowChanges += ms.length; });
        window.__rowWatch.observe(document.querySelector('#overview tbody'),
                                  {childList: true, subtree: true, characterData: true, attributes: true});
    }""")
    try:
        # Pressed through two pushes of the rows (each changes some of the six DCUs' figures), and
        # 1.5 s more to draw them (the page draws the overview at most once a second).
        wait_for(lambda: page.wait_for_timeout(100) or sum(1 for t, event, _ in list(traffic.events)
                                                            if t >= since and event == "overview") >= 2,
                 30, 0.1, "two pushes of the rows during the press")
        page.wait_for_timeout(1500)
        changes = page.evaluate("window.__rowChanges")
    finally:
        page.mouse.up()
    assert changes == 0, f"the rows changed {changes} times during the press"
    wait_for(lambda: address(page) == f"/?open={node}", 5, 0.1, "the click to open the DCU")
    wait_for(lambda: page.evaluate("window.__rowChanges") > 0, 10, 0.2, "the rows drawn after the press")
    page.evaluate("window.__rowWatch.disconnect()")
    click_row(page, node)
    assert address(page) == "/?open="


def test_the_killed_dcu_reads_0_fps_once_its_frames_left_the_window(fleet, page):
    """Killed a test or two ago, silent since: its row, /api/overview and /metrics give it 0 frames/s
    once its last frames are older than the rolling window (10 s), not its rate before."""
    relay, _ = fleet
    page, _ = page
    last = {}

    def decayed():
        row = next(r for r in get_json(f"{relay.url}/api/overview")["rows"] if r["node"] == KILLED)
        last.update(api=row["fps"], cell=cells(page, KILLED)[2], metrics=source_fps(relay.url, KILLED))
        return row["fps"] == 0.0 and last["cell"] == "0.0" and set(last["metrics"].values()) == {0.0}

    try:
        wait_for(decayed, 40, 0.5, f"{KILLED} at 0 frames/s")
    except AssertionError as exc:
        raise AssertionError(f"{exc}: {last}") from None
    assert len(last["metrics"]) == SOURCES
    assert float(cells(page, "DCU-1")[2]) > 0  # the others stream on


def test_two_opened_dcus_are_what_the_moments_view_offers_and_it_says_what_is_missing(fleet, page):
    relay, _ = fleet
    page, _ = page
    line = page.locator("#moments-summary")

    def says(text: str) -> str:
        wait_for(lambda: line.inner_text() == text, 10, 0.2, f"the moments line to say {text!r}, not {line.inner_text()!r}")
        return line.get_attribute("class") or ""

    click_row(page, "DCU-1")
    page.click(".tab[data-tab=moments]")
    # One DCU open of six: open another (said plainly, not as an error).
    assert "field-msg" not in says("Moments need two DCUs open: only DCU-1 is open. Open another in the fleet "
                                   "overview above (click its row).")
    click_row(page, "DCU-2")
    assert address(page) == "/?open=DCU-1,DCU-2"
    wait_for(lambda: page.locator("#moments-a option").all_inner_texts() == ["DCU-1", "DCU-2"], 10, 0.2,
             "the opened DCUs in the moments selectors")
    assert page.locator("#moments-b option").all_inner_texts() == ["DCU-1", "DCU-2"]
    # Both read the simulated cameras, whose frames carry no capture time: the relay says so, and what would.
    verdict = get_json(f"{relay.url}/api/moments?a=DCU-1&b=DCU-2")["summary"]["verdict"]
    assert verdict.startswith("no capture times: moments match the frames of one camera on two DCUs by its capture "
                              "time, which an RTSP camera's RTCP sender reports give")
    assert verdict.endswith("sim://camera0, sim://camera1 are not RTSP, and files and test sources have none")
    assert "field-msg" not in says(verdict)
    page.select_option("#moments-b", "DCU-1")
    assert "field-msg" in says("DCU a and DCU b are both DCU-1: choose two different DCUs.")
    page.click(".tab[data-tab=stage]")
    page.click("#overview-close")
    assert address(page) == "/?open=" and debug(page)["opened"] == []


def test_open_in_the_address_opens_those_dcus_and_star_opens_all(fleet, browser):
    relay, _ = fleet
    page, errors, traffic = open_page(browser, relay.url, "/?open=DCU-2,DCU-4")
    try:
        want = ["DCU-2", "DCU-4"]
        d = wait_for(lambda: (lambda d: d if all(sum(d["stage"]["bars"].get(n, {}).values()) for n in want) else None)(
            debug(page)), 30, 0.3, "both DCUs' bars")
        assert d["opened"] == want and d["chosen"] and d["liveStores"] == want
        assert [r["node"] for r in d["stage"]["rows"]] == want
        wait_for(lambda: sorted(r["node"] for r in debug(page)["overview"]["rows"] if r["open"]) == want, 10, 0.2,
                 "their rows marked open")
        since = time.monotonic()
        page.wait_for_timeout(2000)
        # At least 2 s, until both DCUs' frames came (a loaded machine is slower).
        try:
            seen = wait_for(lambda: (lambda s: s if s >= set(want) else None)(traffic.nodes_in(since)["frames"]), 30,
                            0.2, "both DCUs' frames pushed")
        except AssertionError as exc:
            d = debug(page)
            raise AssertionError(f"{exc}: transport {d['transport']}, subscription {d['subscription']}, frames pushed "
                                 f"before: {traffic.nodes_in(0)['frames']}, received {d['stores']}") from None
        assert seen == set(want)
    finally:
        page.close()
    page, errors2, traffic = open_page(browser, relay.url, "/?open=*")
    try:
        alive = [n for n in NODES if n != KILLED]
        d = wait_for(lambda: (lambda d: d if all(sum(d["stage"]["bars"].get(n, {}).values()) for n in alive) else None)(
            debug(page)), 60, 0.3, "every live DCU's bars")
        # The bars may come from the backfill (HTTP) before the socket connected and subscribed.
        sub = wait_for(lambda: (lambda s: s if s and s["ack"] else None)(debug(page)["subscription"]), 30, 0.2,
                       "the relay's answer to the subscription")
        assert d["opened"] == "*" and sub["nodes"] is None and sub["ack"] == {"ok": True}
        assert d["overview"]["count"] == "6 of 6 DCUs · 6 opened"
    finally:
        page.close()
    assert not errors and not errors2, errors + errors2


def test_without_the_socketio_client_the_overview_and_an_opened_dcu_are_polled(fleet, browser):
    relay, _ = fleet
    page = browser.new_page(viewport={"width": 1400, "height": 950})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.route("**/vendor/socket.io.min.js", lambda route: route.abort())
        page.goto(relay.url + "/")
        d = wait_for(lambda: (lambda d: d if d["overview"]["total"] == len(NODES) else None)(debug(page)), 30, 0.3,
                     "six rows polled")
        assert d["transport"] == "polling" and d["opened"] == [] and d["liveStores"] == []
        click_row(page, "DCU-6")
        d = wait_for(lambda: (lambda d: d if sum(d["stage"]["bars"].get("DCU-6", {}).values()) > 0 else None)(
            debug(page)), 30, 0.3, "DCU-6's bars while polling")
        assert d["liveStores"] == ["DCU-6"] and [n["node"] for n in d["nodes"]] == ["DCU-6"]
    finally:
        page.close()
    assert not errors, errors


def test_rows_turn_stale_then_go_when_their_relay_stops(fleet, page, browser):
    relay, _ = fleet
    page, _ = page
    page.mouse.move(5, 5)
    wait_for(lambda: debug(page)["overview"]["total"] == len(NODES), 30, 0.2, "every row")
    assert page.locator("#overview tbody tr.stale").count() == 0
    # Beside it, a page showing every DCU: rows that expire close none of them.
    every, errors, _ = open_page(browser, relay.url, "/?open=*")
    alive = [n for n in NODES if n != KILLED]
    wait_for(lambda: set(alive) <= set(debug(every)["liveStores"]), 60, 0.3, "every live DCU held")
    # Stopped on a thread of its own: the page is watched meanwhile (a relay may take a while to close).
    stopping = threading.Thread(target=relay.stop, daemon=True)
    stopping.start()
    try:
        # A row is stale from 3 s unrefreshed and dropped at 5 s (ROW_STALE_MS, ROW_DROP_MS): the rows,
        # the table and a row's cells are read in one evaluation, so that a loaded machine's slow
        # polls cannot see one state and then read the next. The table is redrawn from the rows at
        # most once a second: a while after the rows.
        snap = wait_for(lambda: (lambda s: s if s["rows"] and all(r["stale"] for r in s["rows"])
                                 and s["drawnStale"] == len(NODES) else None)(stale_snapshot(page)),
                        20, 0.1, "every row stale, and drawn so")
        assert all(any(a.startswith("stale") for a in r["alerts"]) for r in snap["rows"])
        assert all(r["down"] for r in snap["rows"])  # unheard of: they sort as the DCUs that are down
        assert "stale" in snap["dcu1"][1]
        wait_for(lambda: debug(page)["overview"]["total"] == 0, 15, 0.2, "the rows dropped")
        assert page.locator("#overview tbody tr").count() == 0
        wait_for(lambda: debug(every)["overview"]["total"] == 0, 15, 0.2, "the rows dropped on the other page")
        d = debug(every)
        assert set(alive) <= set(d["liveStores"]) and all(d["stores"][n]["received"] > 0 for n in alive)
    finally:
        every.close()
        stopping.join(30)
    assert not errors, errors
