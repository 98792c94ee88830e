"""The fleet overview's pure JavaScript (ui/static/overview.js), run in Chromium: the worst-first
order, the filter, ?open= in the address, which DCUs are opened, rows merged and aged, and the
table's keyed rows updated in place."""

from __future__ import annotations

import pytest

from tests.ui.helpers import units_page


@pytest.fixture(scope="module")
def page(browser, tmp_path_factory):
    yield from units_page(browser, tmp_path_factory.mktemp("overview-units") / "relay.db")


def js(page, body: str, arg=None):
    """Run ``body`` (an async function body with overview.js as ``m``) in the page."""
    return page.evaluate(
        """async ([body, arg]) => {
            const m = await import("/overview.js");
            return new Function("m", "arg", `return (async () => { ${body} })()`)(m, arg);
        }""", [body, arg])


ROWS_JS = """
    const now = 100000;
    const row = (node, extra) => ({node, run: node + "-run", relay: "relay-a", connected: true, ended: false,
        fps: 30, p99_ms: 40, frames: 10, drops: 0, bottleneck: {stage: "infer", utilization: 0.5},
        clock: {applied: "estimate", offset_us: 3, uncertainty_us: 20}, ptp: null, alerts: [],
        seen: now, keep: 5000, ...extra});
"""


def test_worst_first_is_down_then_alerts_then_bottleneck_utilization_then_p99_then_name(page):
    out = js(page, ROWS_JS + """
        const rows = [
            row("quiet"),
            row("slow", {p99_ms: 90}),
            row("busy", {bottleneck: {stage: "infer", utilization: 0.97}}),
            row("busier-by-a-hair", {bottleneck: {stage: "infer", utilization: 0.9701}, p99_ms: 10}),
            row("three-alerts", {alerts: ["stage infer saturated (97 %)", "PTP lost", "clock uncertain (±1200 µs)"]}),
            row("down", {connected: false, alerts: ["disconnected"], p99_ms: 1}),
            row("ended", {connected: false, ended: true}),  // a run that ended is not down
            row("one-alert", {alerts: ["12 frames dropped or lost in 60 s"]}),
            row("stale", {seen: now - 3500}),              // unheard of: the page's own alert, not refreshed
            row("no-figures", {bottleneck: null, p99_ms: null, fps: null}),
            row("a-twin"), row("z-twin"),
        ];
        return rows.sort((a, b) => m.worstFirst(a, b, now)).map((r) => r.node);""")
    # Down or unheard of first (the two: one alert each, the same utilization, the longer p99 first), then
    # alerts, utilization in whole percent (as shown: 97.01 % ties with 97 %, then p99 decides), p99, name.
    assert out == ["stale", "down", "three-alerts", "one-alert", "busy", "busier-by-a-hair", "slow",
                   "a-twin", "ended", "quiet", "z-twin", "no-figures"]


def test_an_ended_row_says_its_figures_are_its_whole_runs(page):
    """The relay gives an ended run's whole-run p99 (its window empties): the row says whose they are."""
    out = js(page, ROWS_JS + """
        const text = (html) => { const d = document.createElement("div"); d.innerHTML = html; return d.textContent; };
        const cells = (r) => m.rowCells(r, false, now).map(text);
        return {ended: cells(row("vm", {connected: false, ended: true, fps: null, p99_ms: 6.85, figures: "whole run"})),
                live: cells(row("live", {figures: "window"}))};""")
    assert out["ended"][2] == "ended" and out["ended"][3] == "6.85 ms whole run"
    assert out["live"][3] == "40.00 ms"


def test_a_row_whose_relay_went_silent_is_down_says_so_once_and_counts_its_silence_on(page):
    out = js(page, ROWS_JS + """
        const silent = row("silent", {connected: false, state: "relay silent", silent_s: 4.2, stale: true,
                                      alerts: ["relay silent: last heard 4 s ago"], seen: now - 2000});
        const cells = m.rowCells(silent, false, now);
        const order = [row("busy", {alerts: ["PTP lost", "clock uncertain (±1200 µs)"]}), silent]
            .sort((a, b) => m.worstFirst(a, b, now)).map((r) => r.node);
        const derived = m.rowFromNode({node: "n", run: "r", connected: false, ended: false, state: "relay silent",
                                       silent_s: 5.4});
        return {down: m.isDown(silent, now), alerts: m.alertsOf(silent, now), order, dot: cells[0], relay: cells[1],
                derived: [derived.alerts, m.isDown(derived, now)]};""")
    assert out["down"] and out["order"] == ["silent", "busy"]
    assert out["alerts"] == ["relay silent: last heard 4 s ago"]  # the page adds no stale alert of its own
    # 4.2 s silent when the relay answered, 2 s ago: 6 s now.
    assert 'class="dot dot-down" title="relay silent (6 s ago)"' in out["dot"]
    assert out["relay"].startswith("relay-a ") and out["relay"].endswith(">relay silent (6 s ago)</span>")
    assert out["derived"] == [["relay silent: last heard 5 s ago"], True]


def test_filter_matches_every_word_in_dcu_relay_bottleneck_or_alerts(page):
    out = js(page, ROWS_JS + """
        const r = row("DCU-North-7", {relay: "relay-b:8080", bottleneck: {stage: "tiler", utilization: 0.8},
                                      alerts: ["stage tiler saturated (98 %)"]});
        const s = row("DCU-South-1", {seen: now - 4000});
        const t = (text) => m.matches(r, text, now);
        return {dcu: t("north"), relay: t("RELAY-B"), stage: t("tiler"), alert: t("saturated"), words: t("north 8080"),
                miss: t("south"), oneMissing: t("north south"), empty: t("  "), stale: m.matches(s, "stale", now),
                clockIsNotSearched: t("estimate")};""")
    assert out == {"dcu": True, "relay": True, "stage": True, "alert": True, "words": True, "miss": False,
                   "oneMissing": False, "empty": True, "stale": True, "clockIsNotSearched": False}


def test_open_in_the_address_round_trips_any_name_and_keeps_other_parameters(page):
    out = js(page, """
        const names = new Set(["DCU-1", "a,b", "star*", "with space", "ünï/κ", "x&y=z"]);
        const search = m.withOpen("?token=T0K&open=old", names);
        const back = m.parseOpen(search);
        return {search, back: [...back].sort(), all: m.withOpen("?token=T", m.OPEN_ALL),
                parsedAll: m.parseOpen("?open=*"), gone: m.withOpen("?open=A,B&token=T", null),
                none: m.parseOpen("?token=T"), empty: [...m.parseOpen("?open=")], emptyBack: m.withOpen("", new Set())};""")
    assert out["search"].startswith("?token=T0K&open=")
    assert out["back"] == sorted(["DCU-1", "a,b", "star*", "with space", "ünï/κ", "x&y=z"])
    assert out["all"] == "?token=T&open=*" and out["parsedAll"] == "*"
    assert out["gone"] == "?token=T" and out["none"] is None
    # An empty ?open= is a choice too: no DCU opened, whatever the fleet's size.
    assert out["empty"] == [] and out["emptyBack"] == "?open="


def test_a_small_fleet_opens_whole_until_the_user_chooses(page):
    out = js(page, """
        const f = (choice, names) => [...m.openedOf(choice, names)].sort();
        const four = ["A", "B", "C", "D"];
        return {four: f(null, four), five: f(null, [...four, "E"]), chosen: f(new Set(["B", "Z"]), four),
                all: f(m.OPEN_ALL, [...four, "E"]), none: f(new Set(), four), max: m.AUTO_OPEN_MAX};""")
    assert out == {"four": ["A", "B", "C", "D"], "five": [], "chosen": ["B", "Z"], "all": ["A", "B", "C", "D", "E"],
                   "none": [], "max": 4}


def test_rows_merge_by_node_turn_stale_at_3_s_and_go_at_5_s(page):
    out = js(page, """
        const f = new m.Fleet();
        const t = 1e6;
        f.merge([{node: "A", relay: "r1", run: "ra", alerts: []}, {node: "B", relay: "r1", run: "rb"}], t);
        f.merge([{node: "C", relay: "r2", run: "rc", alerts: ["PTP lost"]}], t + 1000);   // another relay's rows
        // An older relay's nodes list: a row for a DCU no overview row covers, none over a fresh overview row.
        f.noteNodes([{node: "A", run: "ra", connected: true}, {node: "D", run: "rd", connected: false, ended: false,
                      frames: {shown: 7}, drops: 2, clock: {applied: "none"}}], t + 1000);
        const a = f.rows.get("A"), d = f.rows.get("D"), runOf = f.runOf("C");
        const at = (ms) => Object.fromEntries([...f.rows.values()].map((r) => [r.node, m.isStale(r, t + ms)]));
        const stale2 = at(2900), stale3 = at(3000);
        const gone1 = f.expire(t + 5001);
        // An HTTP answer while the socket is down lives until the next poll; the relay's own stale mark shows at once.
        f.merge([{node: "E", relay: "r3", run: "re", stale: true}], t + 6000, 11000);
        const e = f.rows.get("E");
        const gone2 = f.expire(t + 12000);
        const gone3 = f.expire(t + 17001);
        return {names: [...f.rows.keys()], a: a.derived, d: {derived: d.derived, alerts: d.alerts, frames: d.frames,
                drops: d.drops, relay: d.relay}, stale2, stale3, gone1, eStale: m.isStale(e, t + 6000),
                eAlerts: m.alertsOf(e, t + 6000), gone2, gone3, runOf};""")
    assert out["a"] is False
    assert out["d"] == {"derived": True, "alerts": ["disconnected"], "frames": 7, "drops": 2, "relay": None}
    assert out["stale2"] == {"A": False, "B": False, "C": False, "D": False}
    assert out["stale3"] == {"A": True, "B": True, "C": False, "D": False}
    assert sorted(out["gone1"]) == ["A", "B"]
    assert out["eStale"] and out["eAlerts"] == ["stale: its relay stopped refreshing it"]
    assert sorted(out["gone2"]) == ["C", "D"] and out["gone3"] == ["E"]
    assert out["runOf"] == "rc" and out["names"] == []


def test_the_table_updates_its_rows_in_place_worst_first_filtered_and_counted(page):
    out = js(page, ROWS_JS + """
        const root = document.createElement("section");
        root.innerHTML = `<input id="overview-filter"><span id="overview-count"></span><span id="overview-order"></span>
            <span id="overview-hint"></span><table><thead><tr></tr></thead><tbody></tbody></table>`;
        document.body.append(root);
        const toggled = [];
        const table = new m.OverviewTable(root, (node) => toggled.push(node));
        const f = new m.Fleet();
        const rows = ["A", "B", "C"].map((n) => row(n));
        f.merge(rows, now);
        table.update(f, new Set(["B"]), now);
        const trs = Object.fromEntries([...root.querySelectorAll("tbody tr")].map((tr) => [tr.dataset.node, tr]));
        const order1 = [...root.querySelectorAll("tbody tr")].map((tr) => tr.dataset.node);
        const writes = [];
        new MutationObserver((ms) => { for (const x of ms) writes.push(x.target.className || x.target.nodeName); })
            .observe(root.querySelector("tbody"), {childList: true, subtree: true});
        // C gets an alert: it moves to the top, its fps and alerts cells are rewritten, nothing else is.
        f.merge([row("C", {alerts: ["disconnected"], fps: 12.5})], now);
        table.update(f, new Set(["B"]), now);
        await new Promise((r) => setTimeout(r, 0));
        const order2 = [...root.querySelectorAll("tbody tr")].map((tr) => tr.dataset.node);
        const same = [...root.querySelectorAll("tbody tr")].every((tr) => trs[tr.dataset.node] === tr);
        const cCells = [...trs.C.children].map((td) => td.textContent);
        root.querySelector("#overview-filter").value = "disconn";
        table.update(f, new Set(["B"]), now);
        const shown = [...root.querySelectorAll("tbody tr")].filter((tr) => !tr.hidden).map((tr) => tr.dataset.node);
        const count = root.querySelector("#overview-count").textContent;
        trs.C.querySelector("td").click();
        const head = [...root.querySelectorAll("thead th")].map((th) => th.textContent);
        const open = [trs.B.classList.contains("open"), trs.A.classList.contains("open")];
        root.remove();
        return {order1, order2, same, writes, cCells, shown, count, toggled, head, open,
                order: root.querySelector("#overview-order").title};""")
    assert out["order1"] == ["A", "B", "C"] and out["order2"] == ["C", "A", "B"] and out["same"]
    # Moving C to the top and rewriting its fps and alerts cells: no other cell, no new row.
    assert sorted(set(out["writes"])) == ["TBODY", "ov-alerts", "ov-fps"], out["writes"]
    assert out["cCells"][0] == "▸C" and out["cCells"][1] == "relay-a" and out["cCells"][2] == "12.5"
    assert out["cCells"][3] == "40.00 ms" and out["cCells"][4] == "infer 50 %" and out["cCells"][6] == "0"
    assert out["cCells"][5].startswith("estimate") and out["cCells"][7] == "1 disconnected"
    assert out["shown"] == ["C"] and out["count"] == "1 of 3 DCUs · 1 opened"
    assert out["toggled"] == ["C"] and out["open"] == [True, False]
    assert out["head"] == ["DCU", "relay", "fps", "frame p99", "bottleneck", "clock", "drops", "alerts"]
    assert out["order"].startswith("Worst first: DCUs down or unheard of first")
