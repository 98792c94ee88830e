"""Honest display of clocks: every cross-node figure carries its uncertainty, and the stage view can
show raw node timestamps and draws each node's clock bound as a band.

A real relay (``--clock auto``: no PTP, so the relay's estimate is applied) fed by two simulated
nodes, DCU-2 with its clock 3 ms ahead. Once both ended: ``/api/stats``, the stored session's
statistics, ``dcuscope stats --db`` and ``dcuscope export --db`` carry the correction and its
bound, equal to the relay's own (:meth:`dcuscope.relay.live.state.RelayState.correction`) and to the stored one;
then the page, on the stored session, moves DCU-2's bars by its offset when switched to raw
timestamps and draws a band as wide as its uncertainty at the zoom in force.
"""

from __future__ import annotations

import csv
import io
import json
import re

import numpy as np
import pytest

from dcuscope.relay.clock.correction import Correction
from dcuscope.relay.clock.entry import clock_entry
from dcuscope.relay.store.runs import load_runs
from tests.probes.synth import run_commands
from tests.relay.helpers import get_json, wait_for
from tests.ui.helpers import KEEP_ENDED, RelayThread, sim_nodes

pytestmark = pytest.mark.long  # its tests share a module fixture: one group of 30 s or more, started first

NODES = ["DCU-1", "DCU-2"]
OFFSET_NS = 3_000_000
GUTTER = 150  # stageview.js
MIN_WIDTH_MS = 1.0  # app.js: the narrowest window the stage view zooms to
MUX = "#e53935"


@pytest.fixture(scope="module")
def ended(tmp_path_factory):
    """A relay whose two nodes streamed and ended; the id of their session."""
    tmp = tmp_path_factory.mktemp("ui-clock")
    relay = RelayThread(tmp / "relay.db", limits=KEEP_ENDED)
    # 10 s: long enough for several clock exchanges (every 2 s) even when a loaded machine delays some,
    # so that each run's clock history holds more than one estimate
    feeder = sim_nodes(relay.url, tmp, NODES, frames=300, sources=3, fps=30, paced=True, offsets_ns=[0, OFFSET_NS])
    try:
        feeder.wait(120)
        wait_for(lambda: all(n["ended"] for n in get_json(f"{relay.url}/api/nodes")), 30, 0.2, "both runs ended")
        session = get_json(f"{relay.url}/api/sessions")[0]["session"]
        yield relay, session, tmp / "relay.db"
    finally:
        feeder.stop()
        relay.stop()


def _relay_correction(relay: RelayThread, node: str) -> Correction:
    state = relay.relay.state
    return relay.call(lambda: state.correction(state.node_run(node)))


def _stored_frames(relay: RelayThread, session: int, node: str) -> list[dict]:
    return get_json(f"{relay.url}/api/sessions/{session}/frames?node={node}&limit=10000")["frames"]


def _figures(entry: dict) -> tuple:
    return entry["applied"], entry["correction_ns"], entry["uncertainty_ns"], entry["at_ns"]


def test_live_and_stored_statistics_carry_the_relays_correction_and_its_bound(ended):
    relay, session, db = ended
    runs = {r.header.node: r for r in load_runs(db, session, corrected=False)}
    from_cli = json.loads(run_commands("stats", "--db", str(db), "--session", str(session), "--json")[1])["nodes"]
    for node in NODES:
        corr = _relay_correction(relay, node)
        live = get_json(f"{relay.url}/api/stats?node={node}")["clock"]
        assert live == clock_entry(corr, live["at_ns"]), node
        assert live["applied"] == "estimate" and 0 < live["uncertainty_ns"] < 2_000_000, live
        truth = OFFSET_NS if node == "DCU-2" else 0
        assert abs(live["correction_ns"] - truth) <= live["uncertainty_ns"], live  # the truth inside the bound
        # No sample came after the run ended: the stored history is the relay's, evaluated at the run's last event.
        assert runs[node].correction.segments == corr.segments and len(corr.segments) >= 2, corr
        stored = get_json(f"{relay.url}/api/sessions/{session}/stats?node={node}")["clock"]
        assert stored == clock_entry(runs[node].correction, runs[node].last_ns)
        assert _figures(stored) == _figures(clock_entry(corr, runs[node].last_ns))
        assert abs(stored["correction_ns"] - truth) <= stored["uncertainty_ns"], stored
        assert from_cli[node]["clock"] == stored, node
        # Each frame by the estimate in force at its origin (node time: the corrected one plus the offset).
        frames = get_json(f"{relay.url}/api/frames?node={node}&limit=2000")
        for f in frames["frames"]:
            assert (f["clock_ns"], f["clock_uncertainty_ns"]) == corr.at(f["origin"] + f["clock_ns"]), f
            assert abs(f["clock_ns"] - truth) <= f["clock_uncertainty_ns"], f
        last = frames["frames"][-1]
        assert (frames["correction_ns"], frames["uncertainty_ns"]) == corr.at(last["end"] + last["clock_ns"])


def test_exports_of_the_stored_session_carry_each_frames_correction_and_bound(ended, tmp_path):
    relay, session, db = ended
    runs = {r.header.node: r for r in load_runs(db, session, corrected=False)}
    # The session API's figures per frame; the exports look them up by corrected times: equal to
    # within rounding (drift x offset).
    expected = {node: {(f["source"], f["frame"]): (f["clock_ns"], f["clock_uncertainty_ns"])
                       for f in _stored_frames(relay, session, node)} for node in NODES}

    def agrees(node: str, source: int, frame: int, got: tuple) -> bool:
        want = expected[node].get((source, frame))
        return want is None or (abs(got[0] - want[0]) <= 2 and abs(got[1] - want[1]) <= 2)

    out = tmp_path / "s.csv"
    assert run_commands("export", "--db", str(db), "--session", str(session), "--format", "csv", "-o", str(out))[0] == 0
    rows = list(csv.DictReader(io.StringIO(out.read_text())))
    assert {r["node"] for r in rows} == set(NODES)
    for r in rows:
        assert agrees(r["node"], int(r["source"]), int(r["frame"]), (int(r["clock_ns"]), int(r["clock_uncertainty_ns"]))), r
    out = tmp_path / "s.json"
    assert run_commands("export", "--db", str(db), "--session", str(session), "-o", str(out))[0] == 0
    doc = json.loads(out.read_text())
    for node in NODES:
        meta = doc["otherData"]["clock"][node]
        entry = clock_entry(runs[node].correction, runs[node].last_ns)
        assert meta["applied"] == "estimate" and abs(meta["correction_ns"] - entry["correction_ns"]) <= 2, meta
        assert abs(meta["uncertainty_ns"] - entry["uncertainty_ns"]) <= 2, (meta, entry)
    names = {e["pid"]: e["args"]["name"] for e in doc["traceEvents"] if e.get("name") == "process_name"}
    slices = [e for e in doc["traceEvents"] if e["ph"] == "X" and e["name"].startswith("frame ")]
    assert slices and all(agrees(names[e["pid"]], e["args"]["source"], e["args"]["frame"],
                                 (e["args"]["clock_ns"], e["args"]["clock_uncertainty_ns"])) for e in slices)
    labels = {names[e["pid"]]: e["args"]["labels"] for e in doc["traceEvents"] if e.get("name") == "process_labels"}
    meta = doc["otherData"]["clock"]["DCU-2"]
    assert labels["DCU-2"] == f"clock estimate: {meta['correction_ns'] / 1e6:+.3f} ms ± {meta['uncertainty_ns'] / 1e3:.1f} µs"


# Runs of mux-coloured pixels (solid or wait tint) along one pixel row of the canvas, from x on.
RUNS_JS = """([y, x0, colours]) => {
    const c = document.querySelector('#stage-canvas');
    const data = c.getContext('2d').getImageData(0, Math.round(y), c.width, 1).data;
    const want = new Set(colours.map((hex) => parseInt(hex.slice(1), 16)));
    const runs = [];
    let start = -1;
    for (let x = x0; x <= c.width; x++) {
        const i = 4 * x;
        const on = x < c.width && want.has((data[i] << 16) | (data[i + 1] << 8) | data[i + 2]);
        if (on && start < 0) start = x;
        if (!on && start >= 0) { runs.push([start, x]); start = -1; }
    }
    return runs;
}"""

# Pixels of the clock band (translucent orange: red well above blue) from the plot's start along one row.
BAND_JS = """([y]) => {
    const c = document.querySelector('#stage-canvas');
    const data = c.getContext('2d').getImageData(0, Math.round(y), c.width, 1).data;
    let n = 0;
    for (let x = %d; x < c.width; x++) {
        if (data[4 * x] - data[4 * x + 2] > 40) n++; else break;
    }
    return n;
}""" % GUTTER


def debug(page) -> dict:
    return page.evaluate("window.dcuscope.debug()")


def _redrawn(page, check, what: str) -> dict:
    """The debug state once ``check`` holds and the stage view drew the window in force."""
    return wait_for(lambda: (lambda d: d if check(d) and d["stage"]["window"] == d["window"] else None)(debug(page)),
                    10, 0.1, what)


def _zoom_to(page, width_ms: float, x: float, y: float) -> dict:
    """Wheel in around (x, y) until the window is at most ``width_ms`` wide."""
    for _ in range(40):
        d = debug(page)
        if d["window"][1] - d["window"][0] <= width_ms:
            return d
        before = d["window"]
        page.mouse.move(x, y)
        page.mouse.wheel(0, -150)
        _redrawn(page, lambda d: d["window"] != before, "the zoom")
    raise AssertionError(f"could not zoom to {width_ms} ms: {debug(page)['window']}")


@pytest.fixture(scope="module")
def session_page(ended, browser):
    relay, session, _ = ended
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(relay.url + "/")
        page.locator("#session-select").focus()
        page.wait_for_selector(f'#session-select option[value="{session}"]', state="attached", timeout=15000)
        page.select_option("#session-select", str(session))
        wait_for(lambda: (lambda d: d["mode"] == "session" and d["loaded"])(debug(page)), 60, 0.3, "the session")
        page.click("#zoom-reset")
        yield page
        assert not errors, errors
    finally:
        page.close()


def _row(d: dict, node: str) -> dict:
    return next(r for r in d["stage"]["rows"] if r["node"] == node and r["source"] is None)


def test_the_toggle_moves_each_nodes_bars_by_its_offset_and_says_which_clock(ended, session_page):
    relay, session, _ = ended
    page = session_page
    # Each frame moves by its own offset (the estimate in force at its origin): microseconds apart.
    offsets = [f["clock_ns"] for f in _stored_frames(relay, session, "DCU-2")]
    said = {f"+{o / 1e6:.3f} ms" for o in offsets}
    assert page.locator("#clock-mode").inner_text() == "Clock: corrected"
    assert "relay's clock" in page.locator("#clock-mode").get_attribute("title")
    box = page.locator("#stage-canvas").bounding_box()
    d = debug(page)
    row = _row(d, "DCU-2")
    lane_y = row["y"] + 6 + 12 * row["lanes"].index("mux") + 5
    # Zoom in around the middle of the session to a window where DCU-2's 3 ms offset is ~100 px.
    d = _zoom_to(page, 40.0, box["x"] + GUTTER + (box["width"] - GUTTER) * 0.5, box["y"] + lane_y)
    assert d["clock"] == "corrected" and not d["stage"]["raw"]
    k = (box["width"] - GUTTER - 10) / (d["window"][1] - d["window"][0])  # px per ms (RIGHT_PAD 10)
    light = page.evaluate("async (c) => (await import('/colours.js')).tint(c)", MUX)
    band = d["stage"]["bands"]["DCU-2"]["w"]
    x0 = GUTTER + int(band) + 2  # right of the band, which tints what it covers
    corrected = [r for r in page.evaluate(RUNS_JS, [lane_y, x0, [MUX, light]]) if r[0] > x0]  # whole bars only

    page.click("#clock-mode")
    d = _redrawn(page, lambda d: d["stage"]["raw"], "the raw view")
    assert d["clock"] == "raw" and page.locator("#clock-mode").inner_text() == "Clock: raw node"
    assert "own clock, uncorrected" in page.locator("#clock-mode").get_attribute("title")
    assert {n: b["label"] for n, b in d["stage"]["bands"].items()} == {n: "raw clock" for n in NODES}
    assert all(b["w"] == 0 for b in d["stage"]["bands"].values())
    raw = page.evaluate(RUNS_JS, [lane_y, GUTTER, [MUX, light]])
    shift = float(np.median(offsets)) / 1e6 * k
    assert shift > 60, (shift, k)
    # Every whole bar seen corrected is there in raw mode, moved right by the node's offset (px
    # edges are rounded: 1 px either way).
    moved = [(a + shift, b + shift) for a, b in corrected if b + shift < box["width"] - 12]
    assert len(moved) >= 2, (corrected, raw)
    for a, b in moved:
        assert any(abs(ra - a) <= 1.5 and abs(rb - b) <= 1.5 for ra, rb in raw), ((a, b), raw)
    # The tooltip says which clock a bar is on: a bar whole in both views (where it is drawn raw).
    ra, rb = moved[-1]
    page.mouse.move(box["x"] + (ra + rb) / 2, box["y"] + lane_y)
    tip = wait_for(lambda: debug(page)["tooltip"], 5, 0.1, "the tooltip")
    assert tip.startswith("DCU-2 · mux") and any(
        tip.splitlines()[-1].startswith(f"raw node clock (the relay subtracts {o} ± ") for o in said), tip

    page.click("#clock-mode")
    d = _redrawn(page, lambda d: not d["stage"]["raw"], "the corrected view")
    page.mouse.move(box["x"] + (ra + rb) / 2 - shift, box["y"] + lane_y)
    tip = wait_for(lambda: (lambda t: t if t and "corrected" in t else None)(debug(page)["tooltip"]), 5, 0.1,
                   "the corrected tooltip")
    assert any(tip.splitlines()[-1].startswith(f"corrected to the relay's clock (estimate: {o} subtracted ± ")
               for o in said), tip
    assert re.search(r" (ms|µs) subtracted ± [\d.,]+ \1\)$", tip), tip  # one unit for the offset and its bound
    page.mouse.move(5, 5)


@pytest.mark.parametrize("clock_ms, bound_ms, raw, says", [
    (-0.001, 0.0051, False, "corrected to the relay's clock (estimate: −1.0 µs subtracted ± 5.1 µs)"),
    (3.0124, 0.051, False, "corrected to the relay's clock (estimate: +3.012 ms subtracted ± 0.051 ms)"),
    (0.2, 1.5, True, "raw node clock (the relay subtracts +0.200 ms ± 1.500 ms)"),
    (0.00001, 0.0051, False, "corrected to the relay's clock (estimate: 0.0 µs subtracted ± 5.1 µs)"),
    (-2500.0, 0.04, False, "corrected to the relay's clock (estimate: −2.500000 s subtracted ± 0.000040 s)"),
])
def test_a_bars_clock_line_gives_the_offset_and_its_bound_in_one_unit(session_page, clock_ms, bound_ms, raw, says):
    line = session_page.evaluate("""async ([clock, bound, raw]) => (await import('/stageview.js')).StageView
        .describeClock({clock, bound, raw, applied: "estimate"})""", [clock_ms, bound_ms, raw])
    assert line == says


def _band_bound_ms(frames: list[dict], window: list[float]) -> tuple[float, float]:
    """The largest bound of the frames in ``window`` (ms, relay clock), taken a microsecond inside
    and outside it (the page's float times), or the newest frame's where none is."""
    def largest(margin: float) -> float:
        t0, t1 = window[0] - margin, window[1] + margin
        inside = [f["clock_uncertainty_ns"] for f in frames if f["origin"] / 1e6 <= t1 and f["end"] / 1e6 >= t0]
        return max(inside, default=frames[-1]["clock_uncertainty_ns"]) / 1e6
    return largest(-1e-3), largest(1e-3)


def test_each_rows_band_is_its_nodes_uncertainty_at_the_zoom_in_force(ended, session_page):
    relay, session, _ = ended
    page = session_page
    frames = {node: _stored_frames(relay, session, node) for node in NODES}
    box = page.locator("#stage-canvas").bounding_box()
    if debug(page)["stage"]["raw"]:
        page.click("#clock-mode")
    bound_ms = max(f["clock_uncertainty_ns"] for node in NODES for f in frames[node]) / 1e6
    plot_w = box["width"] - GUTTER - 10
    middle = box["x"] + GUTTER + plot_w * 0.5, box["y"] + 60
    # Zoom until the band is some 30 px wide: 2 U k = 30.
    _zoom_to(page, 2 * bound_ms * plot_w / 30, *middle)
    for node in NODES:
        # U is the largest bound of the node's frames in the window, often below the session's
        # largest (the bound narrows as samples come): zoom on until this node's band is as wide.
        for _ in range(5):
            d = _redrawn(page, lambda d: not d["stage"]["raw"], "a redraw")
            width_ms, w = d["window"][1] - d["window"][0], d["stage"]["bands"][node]["w"]
            if w >= 20 or width_ms <= MIN_WIDTH_MS:
                break
            _zoom_to(page, max(width_ms * max(w, 1.0) / 30, MIN_WIDTH_MS), *middle)
        k = plot_w / (d["window"][1] - d["window"][0])
        band = d["stage"]["bands"][node]
        low, high = _band_bound_ms(frames[node], d["window"])
        assert low - 1e-9 <= band["uncertaintyMs"] <= high + 1e-9, (band, low, high)
        u_ms = band["uncertaintyMs"]
        assert band["w"] == pytest.approx(2 * u_ms * k, rel=1e-6), (band, k)
        us = u_ms * 1000
        assert band["label"] == (f"± {round(us):,} µs" if us >= 9.95 else f"± {us:.1f} µs"), band
        row = _row(d, node)
        drawn = page.evaluate(BAND_JS, [row["y"] + 2])  # above the row's first lane: only the band
        assert abs(drawn - band["w"]) <= 1.5 and drawn >= 10, (node, drawn, band)
    # The gutter names the clock when hovered.
    row = _row(d, "DCU-2")
    page.mouse.move(box["x"] + 20, box["y"] + row["y"] + 16)
    tip = wait_for(lambda: debug(page)["tooltip"], 5, 0.1, "the gutter tooltip")
    assert tip.splitlines() == ["DCU-2", f"clock estimate: {d['stage']['bands']['DCU-2']['label']}"], tip
    page.mouse.move(5, 5)


def test_live_rows_read_the_bound_of_their_newest_frame(ended, browser):
    relay, _, _ = ended
    page = browser.new_page(viewport={"width": 1200, "height": 800})
    try:
        page.goto(relay.url + "/")
        for node in NODES:
            newest = get_json(f"{relay.url}/api/frames?node={node}&limit=2000")["frames"][-1]
            d = _redrawn(page, lambda d: d["stage"].get("bands", {}).get(node, {}).get("label", "").startswith("±")
                         and d["stores"][node]["received"] > 0, f"{node}'s band")
            band = d["stage"]["bands"][node]
            assert band["uncertaintyMs"] * 1e6 == pytest.approx(newest["clock_uncertainty_ns"], abs=1e-3)
            assert band["applied"] == "estimate"
    finally:
        page.close()
