"""The page's pure JavaScript (time axis, formatting, bounded stores, colours), run in Chromium."""

from __future__ import annotations

import pytest

from tests.ui.helpers import units_page


@pytest.fixture(scope="module")
def page(browser, tmp_path_factory):
    yield from units_page(browser, tmp_path_factory.mktemp("units") / "relay.db")


def js(page, body: str, arg=None):
    """Run ``body`` (an async function body with the page's modules in scope) in the page."""
    return page.evaluate(
        """async ([body, arg]) => {
            const m = {};
            for (const name of ["timefmt", "store", "colours", "panels", "stageview", "coverage", "press", "frameview"]) Object.assign(m, await import(`/${name}.js`));
            return new Function("m", "arg", `return (async () => { ${body} })()`)(m, arg);
        }""", [body, arg])


def test_clock_format_and_millisecond_ticks(page):
    # Local noon on a fixed day, plus 7.25 ms: HH:MM:SS.mmm keeps milliseconds and truncates.
    out = js(page, """
        const t = new Date(2024, 0, 2, 12, 34, 56, 789).getTime() + 0.25;
        const fine = m.clockTicks(t, t + 20, 1000);          // 20 ms over 1000 px
        const coarse = m.clockTicks(t, t + 60000, 1000);     // 1 min over 1000 px
        return {clock: m.formatClock(t), precise: m.formatClockPrecise(t), fine, coarse,
                labels: fine.major.map(m.formatClock)};""")
    assert out["clock"] == "12:34:56.789" and out["precise"] == "12:34:56.789250"
    # 110 px at 0.02 ms/px is 2.2 ms: the next round step is 5 ms, on multiples of 5 ms.
    assert out["fine"]["step"] == 5
    assert out["labels"] == ["12:34:56.790", "12:34:56.795", "12:34:56.800", "12:34:56.805"]
    assert len(out["fine"]["minor"]) == 20  # 1 ms minor ticks
    # 1 min over 1000 px: 10 s steps on the round 10 s of the clock.
    assert out["coarse"]["step"] == 10000 and len(out["coarse"]["major"]) == 6


def test_delay_ring_counts_over_limit_with_eviction(page):
    out = js(page, """
        const r = new m.DelayRing(4, 50);
        const seen = [];
        for (const d of [10, 60, 70, 20, 80, 30]) { r.push(d); seen.push(r.over); }
        r.setLimit(25);
        // No limit: none counted; `since` is the first origin until the ring wraps.
        const n = new m.DelayRing(2);
        n.push(10, 1000);
        n.push(90, 2000);
        const unjudged = {over: n.over, since: n.since, wrapped: n.wrapped};
        n.push(5, 3000);
        n.setLimit(8);
        return {seen, size: r.size, over: r.over, unjudged, after: {over: n.over, wrapped: n.wrapped}};""")
    # Ring of 4: after 6 pushes it holds 70, 20, 80, 30.
    assert out["seen"] == [0, 1, 2, 2, 3, 2]
    assert out["size"] == 4 and out["over"] == 3
    assert out["unjudged"] == {"over": 0, "since": 1000, "wrapped": False}
    assert out["after"] == {"over": 1, "wrapped": True}  # it holds 90 and 5


def test_node_store_is_bounded_and_searchable(page):
    out = js(page, """
        const stages = ["src0", "mux", "infer", "sink"];
        const s = new m.NodeStore("DCU-1", stages, 8, 16);
        const frame = (n, src, originMs, delay) => ({n, source: src, frame: n, origin: originMs * 1e6,
            end: (originMs + delay) * 1e6,
            enter: [null, originMs * 1e6 + 1e6, originMs * 1e6 + 3e6, originMs * 1e6 + delay * 1e6],
            exit: [null, originMs * 1e6 + 2e6, originMs * 1e6 + 5e6, null], delay_ms: delay,
            stage_delay_ms: [null, 1, 2, null]});
        const frames = [];
        for (let n = 1; n <= 12; n++) frames.push(frame(n, n % 2, 1000 * n, 10 + n));
        const has_exit = [false, true, true, false];
        const added = s.ingest({run: "a", stages, has_exit, frames});
        const again = s.ingest({run: "a", stages, has_exit, frames: frames.slice(-3)});   // already held
        const oldest = s.frame[s.slot(0)];
        const first = s.firstEndingAfter(7000);      // frame 7 ends at 7017
        const beyond = s.firstEndingBeyond(9019);    // frame 9 ends at 9019 exactly
        const lanes = s.lanes.map((i) => stages[i]);
        const other = s.ingest({run: "b", stages: ["src0", "mux", "sink"], has_exit: [false, true, false], frames: [
            {n: 1, source: 0, frame: 0, origin: 5e12, end: 5e12 + 1e6, enter: [null, 5e12, 5e12 + 1e6],
             exit: [null, 5e12 + 1e6, null], delay_ms: 1, stage_delay_ms: [null, 1, null]}]});
        return {added, again, size: 8, oldest, first: s.size && first, beyond, lanes, sources: [0, 1],
                afterNewRun: {size: s.size, stages: s.stages, received: s.received, other}};""")
    assert out["added"] == 12 and out["again"] == 0
    assert out["oldest"] == 5  # capacity 8: frames 5..12 kept
    assert out["first"] == 2  # logical index of frame 7 (frames 5, 6 ended before 7000)
    assert out["beyond"] == 5  # frames 5..9 end at or before 9019
    assert out["lanes"] == ["mux", "infer"]  # the relay's has_exit: the sink has an enter only, no bar
    # A run with other stages starts the store afresh.
    assert out["afterNewRun"] == {"size": 1, "stages": ["src0", "mux", "sink"], "received": 1, "other": 1}


def test_stage_bars_cover_only_where_frames_were_and_every_bar_pixel_hovers(page):
    # Frames arrive in the order the relay completes them, not in order of their time at a stage:
    # here the osd of frame 3 lies between those of frames 1 and 2. A run of bars that took frame 3
    # in would have painted the gaps on either side of it, where hovering finds no frame.
    out = js(page, """
        const base = 1.7e12, stages = ["mux", "osd"], osd = [[1000, 1010], [1200, 1210], [1100, 1105]];
        const store = new m.NodeStore("DCU-9", stages, 16, 16);
        store.ingest({run: "r", stages, has_exit: [true, true], frames: osd.map(([a, b], i) => ({n: i + 1,
            source: i, frame: i, origin: (base + a - 50) * 1e6, end: (base + b) * 1e6,
            enter: [(base + a - 50) * 1e6, (base + a) * 1e6], exit: [(base + a - 40) * 1e6, (base + b) * 1e6],
            delay_ms: b + 50 - a, stage_delay_ms: [10, b - a]}))});
        const wrap = document.createElement("div");
        wrap.style.width = "1150px";
        document.body.append(wrap);
        const canvas = document.createElement("canvas");
        wrap.append(canvas);
        const colours = new m.StageColours();
        const view = new m.StageView(canvas, {stores: () => [store], colours, expanded: () => false,
                                              describe: () => "clip"});
        view.draw(base + 900, base + 1300);
        const lane = view.last.samples["DCU-9"].osd, y = lane.y + lane.h / 2;   // the osd lane's middle
        const ctx = canvas.getContext("2d"), dpr = canvas.width / canvas.clientWidth;
        const purple = parseInt(colours.get("osd").slice(1), 16);
        const painted = [], hits = [];
        for (let x = m.GUTTER; x < view.cssWidth; x++) {
            const d = ctx.getImageData(Math.round(x * dpr), Math.round(y * dpr), 1, 1).data;
            if (((d[0] << 16) | (d[1] << 8) | d[2]) !== purple) continue;
            painted.push(x);
            const h = view.hit(x + 0.5, y);
            hits.push(h ? h.stage + ":" + h.frame : null);
        }
        wrap.remove();
        const k = view.plotWidth / 400;
        return {painted, hits, gaps: [[1010, 1100], [1105, 1200]].map(([a, b]) =>
            [m.GUTTER + (a - 900) * k + 2, m.GUTTER + (b - 900) * k - 2])};""")
    assert len(out["painted"]) > 20, out
    assert all(h is not None and h.startswith("osd:") for h in out["hits"]), out["hits"]
    assert {h for h in out["hits"]} == {"osd:0", "osd:1", "osd:2"}
    for lo, hi in out["gaps"]:
        assert not [x for x in out["painted"] if lo < x < hi], (lo, hi, out["painted"])


def test_stage_colours_follow_the_paper_and_palette_is_stable(page):
    out = js(page, """
        const c = new m.StageColours();
        return ["mux", "infer_2", "queue", "tiler", "convert", "osd", "queue_1", "queue"].map((s) => c.get(s));""")
    mux, infer2, queue, tiler, convert, osd, queue1, queue_again = out
    assert (mux, infer2, tiler, convert, osd) == ("#e53935", "#1e88e5", "#fdd835", "#43a047", "#8e24aa")
    # Inserted elements: one palette colour per stage name, the same wherever it shows up.
    assert queue == queue_again == "#fb8c00" and queue1 == "#00897b"


def test_stage_colours_follow_the_element_kind_whatever_the_stage_is_called(page):
    out = js(page, """
        const c = new m.StageColours();
        const early = c.get("pgie");                        // seen before its node's kinds arrived
        c.learn({pgie: "infer", sgie: "infer", mixer: "mux", q: "queue"});
        c.learn({pgie: "identity"});                          // the first node's kind stays
        return [early, c.get("pgie"), c.get("sgie"), c.get("mixer"), c.get("q"), c.entries().length];""")
    early, pgie, sgie, mixer, q, n = out
    assert early == "#fb8c00"  # a palette colour until the kind was known
    assert pgie == sgie == "#1e88e5" and mixer == "#e53935" and q == "#00897b" and n == 4


def test_delay_formats_and_axis(page):
    out = js(page, """
        return {d: [0.5, 12.345, 250, 1234.5].map(m.formatDelay), t: [0, 0.25, 20, 2500].map(m.formatTick),
                nice: [0.7, 3, 41, 120, 2600].map(m.niceCeil), ticks: m.delayTicks(100, 500).values};""")
    assert out["d"] == ["500 µs", "12.35 ms", "250.0 ms", "1.234 s"]
    assert out["t"] == ["0", "250 µs", "20 ms", "2.5 s"]
    assert out["nice"] == [1, 5, 50, 200, 5000]
    assert out["ticks"] == [0, 20, 40, 60, 80, 100]


def test_stage_row_names_never_overlap_the_stage_names(page):
    # One row per source, a long node name, long stage names and long source paths: every text
    # drawn in the gutter is measured where it was drawn (its ink box), and no two may meet.
    out = js(page, """
        const base = 1.7e12, stages = ["src0", "mux_batcher", "infer_primary", "convert_post", "osd_overlay"];
        const store = new m.NodeStore("DCU-with-a-rather-long-node-name-7", stages, 16, 16);
        const ms = (t) => (base + t) * 1e6;
        store.ingest({run: "r", stages, has_exit: [false, true, true, true, true],
            frames: [0, 1, 2].map((s) => ({n: s + 1, source: s, frame: 0, origin: ms(s), end: ms(s + 5),
            enter: [ms(s), ms(s + 1), ms(s + 2), ms(s + 3), ms(s + 4)],
            exit: [null, ms(s + 2), ms(s + 3), ms(s + 4), ms(s + 5)], delay_ms: 5,
            stage_delay_ms: [null, 1, 1, 1, 1]}))});
        const wrap = document.createElement("div");
        wrap.style.width = "900px";
        document.body.append(wrap);
        const canvas = document.createElement("canvas");
        wrap.append(canvas);
        const ctx = canvas.getContext("2d", {alpha: false});
        const boxes = [];
        const fill = ctx.fillText.bind(ctx);
        ctx.fillText = (text, x, y) => {
            const t = ctx.measureText(text);
            boxes.push({text, x0: x - t.actualBoundingBoxLeft, x1: x + t.actualBoundingBoxRight,
                        y0: y - t.actualBoundingBoxAscent, y1: y + t.actualBoundingBoxDescent});
            fill(text, x, y);
        };
        const view = new m.StageView(canvas, {stores: () => [store], colours: new m.StageColours(),
            expanded: () => true, describe: (n, s) => `file:///srv/media/cameras/loading-dock-north-entrance-${s}.mp4`});
        view.draw(base - 5, base + 20);
        wrap.remove();
        const gutter = boxes.filter((b) => b.x0 < m.GUTTER && b.text);
        const overlaps = [];
        gutter.forEach((a, i) => gutter.slice(i + 1).forEach((b) => {
            if (a.x0 < b.x1 && b.x0 < a.x1 && a.y0 < b.y1 && b.y0 < a.y1) overlaps.push([a.text, b.text]);
        }));
        return {texts: gutter.map((b) => b.text), overlaps, right: Math.max(...gutter.map((b) => b.x1))};""")
    texts = out["texts"]
    assert sum(t.startswith("source ") for t in texts) == 3 and sum(t.endswith("0.mp4") for t in texts) == 1, texts
    assert any(t.startswith("▾ DCU-") for t in texts) and "all sources" in texts, texts
    assert not out["overlaps"], out
    assert out["right"] <= 150, out  # inside the gutter, left of the plot


def test_stats_panel_shows_the_relays_shares_and_bottleneck_and_derives_none(page):
    # Figures no page could derive from the means (share 0.25 of a 30 ms stage in a 40 ms frame,
    # the bottleneck on the smaller stage): the panel must show exactly what the relay sent.
    out = js(page, """
        const summary = (mean, share) => ({count: 3, mean_ms: mean, p50_ms: mean, p95_ms: mean, p99_ms: mean,
                                           max_ms: mean, share});
        const whole = {stages: {mux: summary(2, 0.125), infer: summary(30, 0.25)}, gaps: {}, frame: summary(40),
                       bottleneck: {stage: "mux", mean_ms: 2, share: 0.125}, fps: {}, frames: {}};
        const window = {...whole, window_s: 10, stages: {mux: summary(2, null), infer: summary(30, 0.5)},
                        bottleneck: null};
        const colours = new m.StageColours();
        const html = (windowed) => {
            const div = document.createElement("div");
            div.innerHTML = m.statsHtml([["DCU-1", {...whole, window}, ["mux", "infer"]]], colours, windowed);
            return [...div.querySelectorAll("tbody tr[data-stage]")].map((tr) =>
                [tr.dataset.stage, tr.classList.contains("bottleneck"), tr.lastElementChild.textContent]);
        };
        return {whole: html(false), window: html(true)};""")
    assert out["whole"] == [["mux", True, "13%"], ["infer", False, "25%"]]
    assert out["window"] == [["mux", False, "–"], ["infer", False, "50%"]]


def test_each_stats_block_says_its_window_and_frames_and_every_table_counts_them(page):
    """Its title says what every table of the block counts: the window's span and frames, or the whole run's;
    the sources table is the window's (as the relay counts it), the node's own drop counters said whole-run."""
    out = js(page, """
        const s = (n) => ({count: n, mean_ms: 5, p50_ms: 5, p95_ms: 5, p99_ms: 6, max_ms: 7, share: 1});
        const src = (n) => ({"0": {delivered: n, fps: 10, nominal_fps: 10, lost_upstream: 0, decoder_dropped: 0, dropped: {}}});
        const whole = {stages: {mux: s(871)}, gaps: {}, frame: s(871), fps: {}, frames: {complete: 871, incomplete: 1},
                       sources: src(871), span_s: 87.4, dropped: 2, lost: 3};
        const window = {stages: {mux: s(102)}, gaps: {}, frame: s(102), fps: {}, frames: {complete: 102, incomplete: 0},
                        sources: src(103), window_s: 10};
        const block = (windowed) => {
            const div = document.createElement("div");
            div.innerHTML = m.statsHtml([["DCU-1", {...whole, window}, ["mux"]]], new m.StageColours(), windowed);
            return {title: div.querySelector("h3 .muted").textContent,
                    delivered: div.querySelector("table.sources tbody tr td:nth-child(2)").textContent,
                    frames: div.querySelector("tr[data-stage=mux] td:nth-child(2)").textContent,
                    foot: div.querySelector(".stats-foot").textContent.replace(/\\s+/g, " ").trim()};
        };
        return {window: block(true), whole: block(false), span: [m.spanText(7), m.spanText(187), m.spanText(7390)]};""")
    assert out["window"]["title"] == "last 10 s · 102 frames"
    assert out["window"]["frames"] == "102" and out["window"]["delivered"] == "103"
    assert "(probe buffer 2, transport 3: whole run)" in out["window"]["foot"]
    assert "102 complete, 0 incomplete" in out["window"]["foot"]
    assert out["whole"]["title"] == "whole run (1 min 27 s) · 871 frames"
    assert out["whole"]["delivered"] == "871" and "whole run)" not in out["whole"]["foot"]
    assert out["span"] == ["7 s", "3 min 07 s", "2 h 03 min"]


def test_the_legend_lists_only_the_stages_of_the_dcus_shown(page):
    """Coloured as every DCU seen, listed as the shown ones have them: no "queue" beside a DCU without one."""
    out = js(page, """
        const colours = new m.StageColours();
        const store = (node, stages) => {
            const st = new m.NodeStore(node, stages, 16, 16);
            st.ingest({run: node, stages, has_exit: stages.map(() => true), frames: []});
            for (const lane of st.lanes) colours.get(st.stages[lane]);
            return st;
        };
        const one = store("DCU-1", ["mux", "infer", "osd"]);
        const two = store("DCU-2", ["mux", "queue", "infer", "osd"]);
        const names = (stores) => m.legendEntries(colours, stores).map(([stage]) => stage);
        return {one: names([one]), both: names([one, two]), none: names([])};""")
    assert out["one"] == ["mux", "infer", "osd"]
    assert out["both"] == ["mux", "infer", "osd", "queue"]
    assert out["none"] == []


def test_the_frame_counts_say_where_they_start_and_why(page):
    """Two DCUs started together count from different instants when the relay kept fewer seconds of the
    faster one (its newest few thousand frames): each says where it starts and why."""
    out = js(page, """
        const ring = new m.DelayRing(8);
        ring.push(3, new Date(2024, 0, 2, 21, 8, 26).getTime(), 3001);
        const young = new m.DelayRing(8);
        young.push(3, new Date(2024, 0, 2, 21, 7, 14).getTime(), 1);
        const text = (r) => { const d = document.createElement("div"); d.innerHTML = m.sinceText(r); return d.textContent; };
        return {late: text(ring), young: text(young), title: (() => { const d = document.createElement("div");
            d.innerHTML = m.sinceText(ring); return d.querySelector("[title]").title; })()};""")
    assert out["young"] == " since 21:07:14 (its run's start)"
    assert out["late"] == " since 21:08:26 (the relay's oldest kept: 3,000 before it not received)"
    assert "newest few thousand frames" in out["title"] and "3,000 earlier frames" in out["title"]


# --- service and wait (issue 11): the relay splits each stage delay; the page only draws it ------

STAGE_VIEW_JS = """
    // A stage view of `stages` on a canvas `width` px wide, over frames given as
    // [source, {stage: [enter, exit, service, wait]}] in ms after `base` (service/wait null: unknown).
    const base = 1.7e12;
    const view_of = (stages, frames, width, split = true) => {
        const store = new m.NodeStore("DCU-5", stages, 4096, 4096);
        const ns = (t) => t === null ? null : (base + t) * 1e6;
        store.ingest({run: "r", stages, has_exit: stages.map(() => true), frames: frames.map(([src, at], i) => {
            const per = stages.map((s) => at[s] ?? [null, null, null, null]);
            const f = {n: i + 1, source: src, frame: i, origin: ns(per[0][0]), end: ns(per[per.length - 1][1]),
                enter: per.map((p) => ns(p[0])), exit: per.map((p) => ns(p[1])),
                delay_ms: per[per.length - 1][1] - per[0][0],
                stage_delay_ms: per.map((p) => p[1] === null ? null : p[1] - p[0])};
            if (split) Object.assign(f, {stage_service_ms: per.map((p) => p[2]), stage_wait_ms: per.map((p) => p[3])});
            return f;
        })});
        const wrap = document.createElement("div");
        wrap.style.width = `${width}px`;
        document.body.append(wrap);
        const canvas = document.createElement("canvas");
        wrap.append(canvas);
        const colours = new m.StageColours();
        const view = new m.StageView(canvas, {stores: () => [store], colours, expanded: () => false, describe: () => "clip"});
        return {store, view, colours, canvas, wrap};
    };
    // The colour of each CSS px of a lane's middle row, from the plot's left edge.
    const lane_pixels = (v, stage) => {
        const row = v.view.last.rows[0], li = row.lanes.indexOf(stage);
        const y = row.y + 6 + li * 12 + 5, dpr = v.canvas.width / v.canvas.clientWidth;
        const d = v.canvas.getContext("2d").getImageData(0, Math.round(y * dpr), v.canvas.width, 1).data;
        const out = [];
        for (let x = m.GUTTER; x < v.view.cssWidth; x++) {
            const i = 4 * Math.round(x * dpr);
            out.push("#" + ((d[i] << 16) | (d[i + 1] << 8) | d[i + 2]).toString(16).padStart(6, "0"));
        }
        return {out, y};
    };
"""


def test_column_coverage_is_the_share_of_each_column_under_the_union(page):
    out = js(page, """
        const iv = new m.Intervals(2);          // grows past its first capacity
        // Out of order; a batch's four frames sharing one interval count once; one crosses three
        // columns; one starts before the window, one ends after it; an empty one is no time.
        for (const [a, b] of [[3.25, 5.5], [0.5, 1], [0.5, 1], [0.5, 1], [0.5, 1], [1.5, 2], [9.5, 12], [-3, 0.25],
                              [4, 4], [0.75, 0.9]]) iv.add(a, b);
        const exact = Array.from(m.columnCoverage(iv, 0, 10, 10));
        // Random intervals against a brute-force union: 1 µs samples of 2 ms columns.
        let seed = 7;
        const rnd = () => ((seed = (seed * 16807) % 2147483647) / 2147483647);
        const r = new m.Intervals(), pairs = [];
        for (let i = 0; i < 300; i++) {
            const a = rnd() * 110 - 5, b = a + rnd() * rnd() * 6;
            r.add(a, b);
            pairs.push([a, b]);
        }
        // And as a lane's frames come: nearly in time order, a few out of place.
        const near = new m.Intervals(), nearPairs = [];
        for (let i = 0; i < 300; i++) {
            const a = i * 0.35 + (i % 17 === 0 ? -3 : rnd() * 0.5), b = a + rnd() * 0.8;
            near.add(a, b);
            nearPairs.push([a, b]);
        }
        const error = (got, pairs) => {
            let worst = 0;
            for (let c = 0; c < 50; c++) {
                let inside = 0;
                for (let t = c * 2 + 0.0005; t < c * 2 + 2; t += 0.001) inside += pairs.some(([a, b]) => t >= a && t < b);
                worst = Math.max(worst, Math.abs(inside / 2000 - got[c]));
            }
            return worst;
        };
        const worst = Math.max(error(m.columnCoverage(r, 0, 100, 50), pairs), error(m.columnCoverage(near, 0, 100, 50), nearPairs));
        // The sort under it: nearly sorted input (insertion), shuffled (past its budget: the native sort).
        const sorts = [0, 5, 1000].map((shuffle) => {
            const a = new Float64Array(2000).map((_, i) => i + rnd() * 3);
            for (let k = 0; k < shuffle; k++) {
                const i = Math.floor(rnd() * 2000), j = Math.floor(rnd() * 2000);
                [a[i], a[j]] = [a[j], a[i]];
            }
            const want = Float64Array.from(a).sort();
            return m.sortNearly(a).every((v, i) => v === want[i]);
        });
        const none = Array.from(m.columnCoverage(new m.Intervals(), 0, 10, 4));
        return {exact, worst, none, sorts, starts: [m.serviceStart(0, 10, 3), m.serviceStart(0, 10, NaN), m.serviceStart(0, 10, 20),
                                             m.serviceStart(0, 10, 0)]};""")
    assert out["exact"] == pytest.approx([0.75, 0.5, 0, 0.75, 1, 0.5, 0, 0, 0, 0.5], abs=1e-6)
    assert out["worst"] < 0.002, out["worst"]
    assert out["none"] == [0, 0, 0, 0]
    assert out["sorts"] == [True, True, True]
    # Service last: 3 ms of a 10 ms bar start at 7; unknown service is the whole bar (drawn solid as before).
    assert out["starts"] == [7, 0, 0, 10]


def test_stage_bar_is_light_while_waiting_and_solid_while_served(page):
    # One frame at mux: 60 ms waiting for its batch, then 20 ms of service; 1 px = 0.5 ms.
    out = js(page, STAGE_VIEW_JS + """
        const v = view_of(["mux"], [[0, {mux: [1000, 1080, 20, 60]}]], 150 + 200 + 10);
        v.view.draw(base + 1000 - 10, base + 1000 + 90);
        const {out, y} = lane_pixels(v, "mux");
        const hit = v.view.hit(m.GUTTER + 20 + 130, y);
        const tip = m.StageView.describeHit(hit, () => "clip");
        v.wrap.remove();
        return {px: out, solid: v.colours.get("mux"), light: m.tint(v.colours.get("mux")), tip,
                lane: v.view.last.lanes["DCU-5"].mux};""")
    px, solid, light = out["px"], out["solid"], out["light"]
    assert light not in (solid, "#ffffff")
    # Enter at px 20, service from px 140 (60 ms), exit at px 180 less the 1 px seam.
    assert set(px[21:139]) == {light}, px[15:185]
    assert set(px[141:178]) == {solid}, px[15:185]
    assert solid not in px[:20] + px[181:] and light not in px[:20] + px[181:]
    assert out["lane"]["bars"] == 1 and out["lane"]["narrow"] == 0
    assert out["tip"][3].startswith("delay 80.00 ms") and out["tip"][4] == "service 20.00 ms  wait 60.00 ms", out["tip"]


def test_zoomed_out_a_short_stage_shades_its_columns_instead_of_looking_busy(page):
    # 40 frames 110 ms apart: "osd" serves each in 0.3 ms, "infer" in 100 ms; 1 px = 5 ms. Bars
    # at a minimum width of 1 px would paint osd's lane solid at every frame, as if it worked 5 ms
    # of each 110; its columns are shaded by the 6 % of them it covers instead.
    out = js(page, STAGE_VIEW_JS + """
        const frames = [];
        for (let i = 0; i < 40; i++) {
            const t = 1000 + 110 * i;
            frames.push([0, {infer: [t, t + 100, 100, 0], osd: [t + 100, t + 100.3, 0.3, 0]}]);
        }
        const v = view_of(["infer", "osd"], frames, 150 + 1000 + 10);
        v.view.draw(base + 500, base + 5500);
        const osd = lane_pixels(v, "osd").out, infer = lane_pixels(v, "infer").out;
        const lanes = v.view.last.lanes["DCU-5"], samples = v.view.last.samples["DCU-5"];
        const hit = v.view.hit(samples.osd.x + 0.5, samples.osd.y + 5);
        v.wrap.remove();
        const count = (arr, c) => arr.filter((p) => p === c).length;
        return {lanes, osdSolid: count(osd, v.colours.get("osd")), osdTinted: osd.filter((p) => !["#ffffff", "#fafbfc",
                "#eceff1", "#cfd8dc"].includes(p)).length, inferSolid: count(infer, v.colours.get("infer")),
                hit: hit && [hit.stage, hit.frame]};""")
    lanes = out["lanes"]
    assert lanes["osd"]["narrow"] == 40 and lanes["osd"]["bars"] == 0
    assert out["osdSolid"] == 0 and out["osdTinted"] >= 40, out
    # 40 frames x 0.3 ms at 5 ms per px: 2.4 px of solid in all, spread as shades.
    assert lanes["osd"]["service"] == pytest.approx(40 * 0.3 / 5, rel=1e-3)
    assert lanes["infer"]["bars"] == 40 and out["inferSolid"] >= 40 * 19, out
    assert out["hit"] is not None and out["hit"][0] == "osd"


def test_stage_bars_without_service_data_are_solid_as_before(page):
    # An old relay (or Python-backend probes) sends no split: the whole bar is solid, the tooltip
    # says nothing of service or wait; zoomed out, its columns are shaded by what the bars cover.
    out = js(page, STAGE_VIEW_JS + """
        const v = view_of(["mux"], [[0, {mux: [1000, 1080, null, null]}], [1, {mux: [1200, 1200.5, null, null]}]],
                          150 + 200 + 10, false);
        v.view.draw(base + 990, base + 1090);
        const {out, y} = lane_pixels(v, "mux");
        const tip = m.StageView.describeHit(v.view.hit(m.GUTTER + 100, y), () => "clip");
        v.view.draw(base, base + 4000);
        const far = v.view.last.lanes["DCU-5"].mux;
        v.wrap.remove();
        return {px: out, solid: v.colours.get("mux"), tip, far};""")
    assert set(out["px"][21:178]) == {out["solid"]}
    assert len(out["tip"]) == 4 and "service" not in "".join(out["tip"])
    # 4 s over 200 px: 20 ms per px; the 80 ms bar is 4 px, the 0.5 ms one 0.025 px of shade.
    assert out["far"]["bars"] == 1 and out["far"]["narrow"] == 1
    assert out["far"]["service"] == pytest.approx(0.5 / 20, rel=1e-3)


STATS_JS = """
    const summary = (mean, extra = {}) => ({count: 3, mean_ms: mean, p50_ms: mean, p95_ms: mean, p99_ms: 2 * mean,
                                            max_ms: 2 * mean, ...extra});
    const render = (doc, windowed = false) => {
        const div = document.createElement("div");
        div.innerHTML = m.statsHtml([["DCU-1", doc, ["mux", "infer", "osd"]]], new m.StageColours(), windowed);
        const rows = [...div.querySelectorAll("table.stats:not(.sources) tbody tr[data-stage]")].map((tr) =>
            ({stage: tr.dataset.stage, marked: tr.classList.contains("bottleneck"), badge: !!tr.querySelector(".badge"),
              cells: [...tr.children].slice(1).map((td) => td.textContent)}));
        const head = [...div.querySelectorAll("table.stats:not(.sources) thead th")].map((th) => th.textContent);
        const reason = div.querySelector(".bottleneck-reason");
        const sources = [...div.querySelectorAll("table.sources tbody tr")].map((tr) =>
            [...tr.children].map((td) => td.textContent));
        return {rows, head, reason: reason && reason.textContent, saturated: !!reason?.classList.contains("saturated"),
                sources, foot: div.querySelector(".stats-foot").textContent.replace(/\\s+/g, " ").trim()};
    };
"""


def test_stats_panel_shows_service_wait_utilization_and_the_relays_verdict(page):
    # The relay names the bottleneck by utilization: infer (97 % busy), though mux has the larger
    # share of delay (it waits for infer). In the window no stage is saturated: no mark, the reason.
    out = js(page, STATS_JS + """
        const split = (mean, service, wait, utilization, share) => summary(mean, {share, utilization,
            service: summary(service), wait: summary(wait)});
        const whole = {stages: {mux: split(362, 1.5, 360.5, 0.02, 0.76), infer: split(100, 99, 1, 0.97, 0.21),
                                osd: split(0.3, 0.3, 0, null, 0.001)},
                       gaps: {}, frame: summary(478), fps: {"0": 5, "1": 5}, frames: {complete: 9, incomplete: 0},
                       bottleneck: {stage: "infer", utilization: 0.97, saturated: true,
                                    reason: "infer is busy 97 % of the time: frames wait for it upstream",
                                    thread_utilization: 0.98},
                       sources: {"1": {delivered: 40, fps: 4.9, nominal_fps: 5, lost_upstream: 2, decoder_dropped: 0,
                                       dropped: {late: 3, stalled: 0, overflow: 1}},
                                 "0": {delivered: 50, fps: 5.0, nominal_fps: null, lost_upstream: 0, decoder_dropped: 1,
                                       dropped: {}}}};
        const window = {...whole, window_s: 10, bottleneck: {stage: "infer", utilization: 0.4, saturated: false,
                        reason: "no stage saturated: infer is the busiest, 40 % of the time", thread_utilization: null}};
        return {whole: render({...whole, window}), window: render({...whole, window}, true)};""")
    whole, window = out["whole"], out["window"]
    assert whole["head"] == ["stage", "frames", "mean", "p50", "p95", "p99", "max", "service mean", "service p99",
                             "wait mean", "utilization", "share of delay"]
    rows = {r["stage"]: r for r in whole["rows"]}
    assert [r["stage"] for r in whole["rows"]] == ["mux", "infer", "osd"]
    assert rows["infer"]["marked"] and rows["infer"]["badge"] and not rows["mux"]["marked"]
    assert rows["infer"]["cells"][6:] == ["99.00 ms", "198.0 ms", "1.00 ms", "97%", "21%"]
    assert rows["mux"]["cells"][6:] == ["1.50 ms", "3.00 ms", "360.5 ms", "2%", "76%"]
    assert rows["osd"]["cells"][9] == "–"  # utilization unknown
    assert whole["reason"] == "infer is busy 97 % of the time: frames wait for it upstream" and whole["saturated"]
    assert whole["sources"] == [["source 0", "50", "5.0", "0", "1", "0"],
                                ["source 1", "40", "4.9 of 5.0", "2", "0", "late 3 · overflow 1"]]
    assert not whole["foot"].startswith("fps")  # the sources table says it per source
    assert not any(r["marked"] or r["badge"] for r in window["rows"])
    assert window["reason"] == "no stage saturated: infer is the busiest, 40 % of the time" and not window["saturated"]


def test_stats_panel_from_an_older_relay_shows_what_it_always_did(page):
    out = js(page, STATS_JS + """
        const old = {stages: {mux: summary(2, {share: 0.125}), infer: summary(30, {share: 0.75})}, gaps: {},
                     frame: summary(40), fps: {"0": 29.5}, frames: {complete: 3, incomplete: 1}, dropped: 2, lost: 0,
                     bottleneck: {stage: "infer", mean_ms: 30, share: 0.75}};
        // A newer relay over a trace with no service data: the new fields are there, null.
        const bare = {...old, stages: {mux: summary(2, {share: 0.125, service: null, wait: null, utilization: null}),
                                       infer: summary(30, {share: 0.75, service: null, wait: null, utilization: null})},
                      bottleneck: null, sources: null};
        return {old: render(old), bare: render(bare)};""")
    for doc in ("old", "bare"):
        r = out[doc]
        assert r["head"] == ["stage", "frames", "mean", "p50", "p95", "p99", "max", "share of delay"], r
        assert [row["cells"][-1] for row in r["rows"]] == ["13%", "75%"] and r["sources"] == []
        assert r["foot"].startswith("fps source 0: 29.5") and r["reason"] is None
    assert [row["marked"] for row in out["old"]["rows"]] == [False, True]
    assert not any(row["marked"] for row in out["bare"]["rows"])


# --- the Nodes panel at a glance (issue 21): one short clock state, the reasons a click away ------

def test_nodes_panel_states_the_clock_in_a_word_and_keeps_every_fact_in_the_detail(page):
    out = js(page, """
        const sysclock = (follows, synced, by, detail) => ({follows_ptp: follows, synced, by, detail});
        const locked = {state: "locked", reason: "slave of aabbcc.fffe.000001", port_state: "SLAVE", master_offset_ns: -12,
                        gm_present: true, gm_identity: "aabbcc.fffe.000001", timestamping: "hardware", interface: "eth0"};
        const est = {applied: "estimate", mode: "auto", offset_us: -3.2, uncertainty_us: 9, drift_ppm: 0.03,
                     drift_uncertainty_ppm: 0.85, correction_us: -3.2, correction_uncertainty_ns: 11000, samples: 32,
                     points: 3, rtt_us: 8, via: "udp", history: 2, restarts: 0, rejected: 0};
        const nodes = [
            {node: "A", run: "r1", connected: true, events: 10, frames: {shown: 5}, drops: 0,
             clock: {...est, applied: "ptp", why: "PTP locked to aabbcc.fffe.000001, offset -12 ns, CLOCK_REALTIME by phc2sys"},
             ptp: {...locked, system_clock: sysclock(true, true, "phc2sys", "phc2sys -s eth0")}},
            {node: "B", run: "r2", connected: true, events: 10, frames: {shown: 5}, drops: 0,
             clock: {...est, why: "PTP not trusted: ptp4l locked but CLOCK_REALTIME not disciplined by PTP (ptp4l free_running, no phc2sys); estimate applied"},
             ptp: {...locked, system_clock: sysclock(false, true, "chronyd", "ptp4l free_running, no phc2sys")}},
            {node: "C", run: "r3", connected: true, events: 1, frames: {shown: 0}, drops: 0,
             clock: {applied: "none", mode: "auto", offset_us: null, why: "PTP not trusted: PTP lost (lost aabbcc.fffe.000001: grandmaster gone); no clock estimate yet"},
             ptp: {state: "lost", reason: "lost aabbcc.fffe.000001: grandmaster gone", gm_present: false}},
            {node: "D", run: "r4", connected: false, ended: true, events: 1, frames: {shown: 0}, drops: 0,
             clock: {...est, offset_us: -0.4, why: "PTP not trusted: PTP unlocked (no grandmaster (port LISTENING)); estimate applied"},
             ptp: {state: "unlocked", reason: "pmc says so", port_state: "LISTENING", gm_present: false}},
        ];
        const render = (open, stored = false, list = nodes) => {
            const div = document.createElement("div");
            div.innerHTML = m.nodesHtml(list, stored, new Set(open));
            return div;
        };
        const closed = render([]);
        const rows = [...closed.querySelectorAll("tr.node-row")].map((tr) => ({
            node: tr.dataset.node, state: tr.querySelector(".clock-state").textContent,
            ptp: tr.querySelector(".ptp-state").textContent, offset: tr.querySelector(".clock-offset").textContent,
            title: tr.querySelector(".clock-cell").title, text: tr.textContent}));
        const opened = render(["B", "D"]);
        const detail = (node) => {
            const tr = opened.querySelector(`tr[data-detail="${node}"]`);
            return {why: tr.querySelector(".clock-why").textContent, ptp: tr.querySelector(".ptp-cell").textContent,
                    sysclock: tr.querySelector(".sysclock").textContent, howto: tr.querySelector(".clock-howto").textContent,
                    text: tr.textContent, span: tr.firstElementChild.colSpan,
                    columns: opened.querySelector("thead tr").children.length};
        };
        const stored = render([], true, [{node: "E", run: "r5", ended: true, events: 1, frames: 0, dropped: 0, lost: 0,
            clock: {applied: "ignored", ignored: "offset beyond any relay's bound", why: ""}},
            {node: "F", run: "r6", ended: false, events: 1, frames: 0, dropped: 0, lost: 0, clock: {applied: "none"}}]);
        return {rows, details: closed.querySelectorAll("tr.node-detail").length, b: detail("B"), d: detail("D"),
                open: [...opened.querySelectorAll("tr.node-detail")].map((tr) => tr.dataset.detail),
                stored: [...stored.querySelectorAll(".clock-state")].map((s) => s.textContent),
                storedTitle: stored.querySelector(".clock-cell").title};""")
    rows = {r["node"]: r for r in out["rows"]}
    assert {n: (r["state"], r["ptp"]) for n, r in rows.items()} == {
        "A": ("PTP locked", "locked"), "B": ("estimate", "locked"), "C": ("no estimate yet", "lost"), "D": ("estimate", "unlocked")}
    assert rows["B"]["offset"] == "−3 µs ± 9 µs" and rows["C"]["offset"] == "–" and rows["D"]["offset"] == "0 µs ± 9 µs"
    for r in out["rows"]:
        assert "PTP not trusted" not in r["text"] and "grandmaster gone" not in r["text"] and len(r["text"]) < 100, r
        assert "docs/clocks.md" in r["title"]
    assert rows["B"]["title"].startswith("PTP not trusted: ptp4l locked but CLOCK_REALTIME not disciplined by PTP")
    assert out["details"] == 0 and out["open"] == ["B", "D"]
    b, d = out["b"], out["d"]
    assert b["span"] == b["columns"] == 10
    assert b["why"].startswith("PTP not trusted: ptp4l locked but") and "docs/clocks.md" in b["howto"]
    # Every PTP fact the columns showed before: port, master offset, grandmaster, timestamping, the system clock.
    assert all(s in b["ptp"] for s in ("locked", "port SLAVE", "offset -12 ns", "GM aabbcc.fffe.000001", "hardware timestamps"))
    assert b["sysclock"] == "chronyd · not PTP · ptp4l free_running, no phc2sys"
    assert "subtracts −3 µs ± 11 µs now" in b["text"] and "32 samples" in b["text"] and "--clock auto" in b["text"]
    # PTP's own reason shows where the clock's reason does not hold it, and only once where it does.
    assert "pmc says so" in d["ptp"] and b["text"].count("slave of aabbcc.fffe.000001") == 1
    assert out["stored"] == ["ignored", "uncorrected"] and "offset beyond any relay's bound" in out["storedTitle"]


def test_a_press_is_under_way_from_its_pointerdown_until_its_release_or_the_page_losing_the_focus(page):
    out = js(page, """
        const box = document.createElement("div"), inside = document.createElement("button"),
              other = document.createElement("button");
        box.appendChild(inside);
        document.body.append(box, other);
        const press = (el) => el.dispatchEvent(new PointerEvent("pointerdown", {bubbles: true}));
        const states = {before: m.pressedWithin(box)};
        press(inside);
        other.focus(); inside.focus(); other.dispatchEvent(new FocusEvent("blur"));  // an element's blur: still pressed
        states.pressed = [m.pressedWithin(box), m.pressedWithin(inside), m.pressedWithin(other)];
        window.dispatchEvent(new PointerEvent("pointerup"));
        states.released = m.pressedWithin(box);
        press(inside);
        window.dispatchEvent(new FocusEvent("blur"));
        states.pageBlurred = m.pressedWithin(box);
        press(other);
        states.elsewhere = m.pressedWithin(box);
        window.dispatchEvent(new PointerEvent("pointercancel"));
        box.remove(); other.remove();
        return states;""")
    assert out == {"before": False, "pressed": [True, True, False], "released": False, "pageBlurred": False,
                   "elsewhere": False}
