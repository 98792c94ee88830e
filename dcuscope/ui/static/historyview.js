// History view: one DCU over minutes to months, from the relay's rollups (GET /api/history). Per
// stage, and for the frame end to end, p99 (solid) and p50 (dashed) of each minute or hour; a time
// without frames breaks the line (a gap is a gap, never a slope). Above it, the statistics of the
// whole span: counts, means, min, max exact, percentiles from the sketch (within 1 % of the value).
// The span opens fitted to the DCU's data, ending at its newest event (never in the future); the span
// select: back to that, or a span ending now; wheel: zoom in or out around the pointer; drag: pan.
// While the tab is shown and not zoomed or panned, the view asks again every REFRESH_MS, so that a
// live DCU's new minutes come by themselves. Frames not rolled up yet are counted from the raw batches.

import { StageColours } from "./colours.js";
import { esc } from "./panels.js";
import { delayTicks, formatTick, niceCeil } from "./timefmt.js";

const H = 280;
const LEFT = 60;
const RIGHT = 16;
const TOP = 24;
const BOTTOM = 40;
const MIN_SPAN_NS = 5 * 60e9;
const MAX_SPAN_NS = 400 * 86400e9;
const HOUR_NS = 3600e9;
const FIT = "fit";
const FRAME_COLOUR = "#263238";
const REFRESH_MS = 15000; // a relay adds rollups at each compaction pass (every 30 s by default)
const CHAR_PX = 7; // an axis label's character (11 px) at its widest: labels are placed whole
const DOT_PX = 8; // points at least this far apart are drawn as dots too (a lone minute shows)
const MINUTE_NS = 60e9;
const DAY_NS = 86400e9;
const X_STEPS_NS = [1, 2, 5, 10, 15, 30].map((m) => m * MINUTE_NS)
  .concat([1, 2, 3, 6, 12].map((h) => h * HOUR_NS), [1, 2, 7, 14, 30, 60, 90].map((d) => d * DAY_NS));

const q = encodeURIComponent;

export class HistoryView {
  /** `colours`: the page's StageColours, so that a stage has the colour it has in the live views. */
  constructor(section, api, colours) {
    this.api = api;
    this.colours = colours;
    this.own = new StageColours(); // stages no live view has coloured: not added to the live legend
    this.nodeSel = section.querySelector("#history-node");
    this.spanSel = section.querySelector("#history-span");
    this.chart = section.querySelector("#history-chart");
    this.table = section.querySelector("#history-summary");
    this.note = section.querySelector("#history-note");
    this.nodes = new Map(); // node -> {first_ns, last_ns} (hours)
    this.window = null; // [since_ns, until_ns] while zoomed or panned; null: the span select's
    this.drawn = null; // [since_ns, until_ns] on screen
    this.timer = null;
    this.seq = 0;
    this.nodeSel.addEventListener("change", () => { this.window = null; this.load(); });
    this.spanSel.addEventListener("change", () => { this.window = null; this.load(); });
    this.chart.addEventListener("wheel", (e) => this.zoom(e), { passive: false });
    this.chart.addEventListener("mousedown", (e) => this.drag(e));
  }

  async show(on) {
    clearInterval(this.timer);
    this.timer = null;
    if (!on) return;
    this.timer = setInterval(() => { if (!this.window) this.refresh(); }, REFRESH_MS);
    await this.refresh();
  }

  async refresh() {
    try {
      const nodes = await this.api.get("/api/history/nodes");
      this.nodes = new Map(nodes.map((n) => [n.node, n]));
      const names = nodes.map((n) => n.node);
      const chosen = this.nodeSel.value;
      if (names.join("\n") !== [...this.nodeSel.options].map((o) => o.value).join("\n")) {
        this.nodeSel.innerHTML = names.map((n) => `<option value="${esc(n)}">${esc(n)}</option>`).join("");
        if (names.includes(chosen)) this.nodeSel.value = chosen;
      }
      if (!names.length) {
        this.say(await this.whenData());
        this.chart.replaceChildren();
        this.legend([]);
        this.table.innerHTML = "";
        return;
      }
    } catch (err) {
      this.say(`History unavailable: ${err.message}`);
      return;
    }
    await this.load();
  }

  /** Why there is nothing yet: no DCU stored an event (a DCU is listed from its first stored batch). */
  async whenData() {
    let health = null;
    try {
      health = await this.api.get("/api/health");
    } catch (_) { /* said without the relay's figures */ }
    const c = health?.compaction;
    const rolled = health && !c ? "this relay does not compact (--compact-after 0): its DCUs are counted from their batches"
      : `its minutes are counted from the batches until the relay rolls them up (within ${c ? `${Math.round(c.rollups_within_s)} s` : "about two minutes"} of a run's start)`;
    return `No DCU has stored anything yet. A DCU shows here once the relay stored its first events; ${rolled}. ` +
      `This view looks again every ${REFRESH_MS / 1000} s.`;
  }

  say(text) {
    this.note.textContent = text;
  }

  /** The span to ask for: the window, the node's whole data (hours: fitted once answered), or a span ending now. */
  asked(node) {
    if (this.window) return this.window;
    const known = this.nodes.get(node);
    const now = Date.now() * 1e6;
    if (this.spanSel.value === FIT && known) return [known.first_ns, Math.min(known.last_ns + HOUR_NS, now)];
    return [now - Number(this.spanSel.value === FIT ? 86400 : this.spanSel.value) * 1e9, now];
  }

  async load() {
    const node = this.nodeSel.value;
    if (!node) return;
    let [since, until] = this.asked(node);
    const fit = !this.window && this.spanSel.value === FIT;
    const seq = ++this.seq;
    let doc;
    try {
      doc = await this.api.get(`/api/history?node=${q(node)}&since=${Math.max(1, Math.round((until - since) / 1e9))}s` +
                               `&until_ns=${BigInt(Math.round(until))}`);
    } catch (err) {
      if (seq === this.seq) this.say(`History of ${node} unavailable: ${err.message}`);
      return;
    }
    if (seq !== this.seq) return; // a newer request went out meanwhile
    if (fit) [since, until] = fitted(doc.history, Date.now() * 1e6) ?? [since, until];
    this.doc = doc;
    this.draw(doc.history, since, until);
    this.summary(doc.summary);
    const width = doc.history.width_ns === 60e9 ? "minute" : "hour";
    this.say(`${node}: ${fit ? "all its data, " : ""}${stamp(since)} to ${stamp(until)} UTC · a point per ${width} · ` +
             "p99 solid, p50 dashed · a break in a line: no frames then");
  }

  width() {
    return Math.max(300, Math.round(this.chart.clientWidth || 1000));
  }

  colour(name, kinds) {
    if (name === "frame") return FRAME_COLOUR;
    if (this.colours?.has(name)) return this.colours.get(name);
    this.own.learn(kinds);
    return this.own.get(name);
  }

  draw(h, since, until) {
    this.drawn = [since, until];
    const W = this.width();
    const lines = [["frame", h.frame], ...Object.entries(h.stages)];
    const top = niceCeil(Math.max(1e-3, ...lines.flatMap(([, pts]) => pts.map((p) => p.p99_ms))));
    const plotW = W - LEFT - RIGHT;
    // A minute's point is drawn at its middle, or at the span's end where that is past it (the newest minute).
    const x = (t) => LEFT + ((Math.min(t, until) - since) / (until - since)) * plotW;
    const y = (ms) => TOP + (1 - ms / top) * (H - TOP - BOTTOM);
    const svg = [`<text class="axis axis-title" x="4" y="${TOP - 10}">delay · p99 solid, p50 dashed</text>`];
    for (const ms of delayTicks(top, H - TOP - BOTTOM, 40).values) {
      svg.push(`<line class="grid" x1="${LEFT}" x2="${W - RIGHT}" y1="${y(ms)}" y2="${y(ms)}"/>`,
               `<text class="axis axis-y" x="${LEFT - 6}" y="${y(ms) + 4}" text-anchor="end">${formatTick(ms)}</text>`);
    }
    for (const { t, label } of timeTicks(since, until, plotW)) {
      const half = (label.length * CHAR_PX) / 2;
      if (x(t) - half < 0 || x(t) + half > W) continue; // a label is shown whole or not at all
      svg.push(`<line class="tick" x1="${x(t)}" x2="${x(t)}" y1="${H - BOTTOM}" y2="${H - BOTTOM + 4}"/>`,
               `<text class="axis axis-x" x="${x(t)}" y="${H - BOTTOM + 16}" text-anchor="middle">${label}</text>`);
    }
    svg.push(`<text class="axis axis-title" x="${LEFT + plotW / 2}" y="${H - 4}" text-anchor="middle">time (UTC)</text>`);
    const dots = plotW * (h.width_ns / (until - since)) >= DOT_PX;
    for (const [name, pts] of lines) {
      const colour = this.colour(name, h.kinds);
      for (const [key, dash] of [["p99_ms", ""], ["p50_ms", ` stroke-dasharray="4 3"`]]) {
        svg.push(`<path class="history-line" data-stage="${esc(name)}" data-q="${key}" stroke="${colour}"${dash} ` +
                 `d="${pathOf(pts, key, h.width_ns, x, y)}"><title>${esc(name)} ${key.slice(0, 3)}</title></path>`);
        if (dots) {
          svg.push(`<path class="history-dots" data-stage="${esc(name)}" data-q="${key}" stroke="${colour}" ` +
                   `fill="${key === "p99_ms" ? colour : "#fff"}" d="${dotsOf(pts, key, h.width_ns, x, y)}"/>`);
        }
      }
    }
    this.chart.setAttribute("viewBox", `0 0 ${W} ${H}`);
    this.chart.innerHTML = svg.join("");
    this.legend(lines.map(([name]) => [name, this.colour(name, h.kinds)]));
  }

  legend(entries) {
    const el = this.chart.parentElement.querySelector(".history-legend");
    el.innerHTML = entries.map(([name, colour]) => `<span class="legend-item" data-stage="${esc(name)}"><span class="swatch" ` +
      `style="background:${colour}"></span>${esc(name === "frame" ? "frame (end to end)" : name)}</span>`).join("");
  }

  summary(s) {
    const rows = [...Object.entries(s.stages).map(([k, v]) => [`stage ${k}`, v]), ["frame (end to end)", s.frame]];
    const cell = (v) => (v === null || v === undefined ? "–" : typeof v === "number" && !Number.isInteger(v) ? v.toFixed(3) : v);
    this.table.innerHTML = `<table class="history-table"><thead><tr><th></th><th>frames</th><th>mean ms</th>` +
      `<th>min ms</th><th title="from the sketch: within ${s.relative_error * 100} % of the value">p50 ms ±1 %</th>` +
      `<th title="from the sketch">p90 ms ±1 %</th><th title="from the sketch">p99 ms ±1 %</th><th>max ms</th><th>drops</th></tr></thead><tbody>` +
      rows.map(([name, v]) => `<tr><td>${esc(name)}</td><td>${v.count}</td><td>${cell(v.mean_ms)}</td><td>${cell(v.min_ms)}</td>` +
        `<td>${cell(v.p50_ms)}</td><td>${cell(v.p90_ms)}</td><td>${cell(v.p99_ms)}</td><td>${cell(v.max_ms)}</td>` +
        `<td>${v.drops ?? ""}</td></tr>`).join("") + `</tbody></table>` +
      `<p class="hint">Exact: frames, mean, min, max, drops (${s.frame.incomplete} incomplete frames, ${s.frame.lost} events lost). ` +
      `p50, p90, p99 from the sketch, within ${s.relative_error * 100} % of the value.</p>` +
      (s.raw?.said ? `<p class="hint history-raw">${esc(s.raw.said)}</p>` : "");
  }

  zoom(e) {
    e.preventDefault();
    if (!this.drawn) return;
    const [since, until] = this.drawn;
    const box = this.chart.getBoundingClientRect();
    const W = this.width();
    const frac = Math.min(1, Math.max(0, ((e.clientX - box.left) / box.width * W - LEFT) / (W - LEFT - RIGHT)));
    const at = since + frac * (until - since);
    const span = Math.min(MAX_SPAN_NS, Math.max(MIN_SPAN_NS, (until - since) * (e.deltaY > 0 ? 1.5 : 1 / 1.5)));
    this.window = [at - frac * span, at + (1 - frac) * span];
    this.load();
  }

  drag(e) {
    if (!this.drawn) return;
    const [since, until] = this.drawn;
    const box = this.chart.getBoundingClientRect();
    const W = this.width();
    const perPx = (until - since) / (box.width * (W - LEFT - RIGHT) / W);
    const start = e.clientX;
    const up = (u) => {
      window.removeEventListener("mouseup", up);
      const shift = (start - u.clientX) * perPx;
      if (Math.abs(u.clientX - start) < 3) return;
      this.window = [since + shift, until + shift];
      this.load();
    };
    window.addEventListener("mouseup", up);
  }
}

/**
 * [since, until] around every point of a history, ending at its newest event (`newest_ns`; else the end
 * of its last minute or hour), never after `now`: at least MIN_SPAN_NS, widened to the left; or null
 * when it has none.
 */
export function fitted(h, now = Infinity) {
  const ts = [h.frame, ...Object.values(h.stages)].flat().map((p) => p.t_ns);
  if (!ts.length) return null;
  const first = Math.min(...ts);
  const until = Math.min(h.newest_ns ?? Math.max(...ts) + h.width_ns, now);
  const span = Math.max(MIN_SPAN_NS, (until - first) * 1.04);
  return [until - span, until];
}

/** Labelled ticks of a UTC time axis over [since, until] drawn `px` wide: round steps, labels apart. */
export function timeTicks(since, until, px) {
  const long = until - since > 2 * DAY_NS;
  const chars = long ? 10 : 11; // "2026-11-24", "11-24 09:30"
  const step = X_STEPS_NS.find((s) => (s / (until - since)) * px >= chars * CHAR_PX + 24) ?? X_STEPS_NS.at(-1);
  const out = [];
  let day = null;
  for (let t = Math.ceil(since / step) * step; t <= until && out.length < 200; t += step) {
    const iso = new Date(t / 1e6).toISOString();
    if (long || step >= DAY_NS) out.push({ t, label: iso.slice(0, 10) });
    else {
      out.push({ t, label: iso.slice(0, 10) === day ? iso.slice(11, 16) : `${iso.slice(5, 10)} ${iso.slice(11, 16)}` });
      day = iso.slice(0, 10);
    }
  }
  return out;
}

/** An SVG path through the points, broken wherever two follow more than one width apart. */
export function pathOf(pts, key, width, x, y) {
  const runs = [];
  let last = null;
  for (const p of pts) {
    if (p[key] === null) { last = null; continue; }
    if (last === null || p.t_ns - last > width) runs.push([]);
    runs[runs.length - 1].push(`${x(p.t_ns + width / 2).toFixed(1)},${y(p[key]).toFixed(1)}`);
    last = p.t_ns;
  }
  // A lone point is a short dash, so that a minute between two gaps still shows.
  return runs.map((r) => `M${r.join("L")}${r.length === 1 ? "h2" : ""}`).join("");
}

/** A dot (radius 2.5) at each point, as an SVG path. */
export function dotsOf(pts, key, width, x, y) {
  return pts.filter((p) => p[key] !== null).map((p) =>
    `M${(x(p.t_ns + width / 2) - 2.5).toFixed(1)},${y(p[key]).toFixed(1)}a2.5,2.5 0 1,0 5,0a2.5,2.5 0 1,0 -5,0`).join("");
}

function stamp(ns) {
  return new Date(ns / 1e6).toISOString().slice(0, 16).replace("T", " ");
}
