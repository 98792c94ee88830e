// History view: one DCU over hours to months, from the relay's rollups (GET /api/history). Per stage,
// and for the frame end to end, p99 (solid) and p50 (dashed) of each minute or hour; a time without
// frames breaks the line (a gap is a gap, never a slope). Above it, the statistics of the whole
// span: counts, means, min, max exact, percentiles from the sketch (within 1 % of the value).
// Wheel: zoom in or out around the pointer; drag: pan; the span select: back to a span ending now.

import { esc } from "./panels.js";

const SVG = "http://www.w3.org/2000/svg";
const H = 280;
const LEFT = 56;
const RIGHT = 12;
const TOP = 10;
const BOTTOM = 24;
const MIN_SPAN_NS = 10 * 60e9;
const MAX_SPAN_NS = 400 * 86400e9;
const COLOURS = ["#1e88e5", "#e53935", "#43a047", "#fb8c00", "#8e24aa", "#00897b", "#6d4c41", "#3949ab"];

const q = encodeURIComponent;

export class HistoryView {
  constructor(section, api) {
    this.api = api;
    this.nodeSel = section.querySelector("#history-node");
    this.spanSel = section.querySelector("#history-span");
    this.chart = section.querySelector("#history-chart");
    this.table = section.querySelector("#history-summary");
    this.note = section.querySelector("#history-note");
    this.window = null; // [since_ns, until_ns] while zoomed or panned; null: the span ending now
    this.seq = 0;
    this.nodeSel.addEventListener("change", () => this.load());
    this.spanSel.addEventListener("change", () => { this.window = null; this.load(); });
    this.chart.addEventListener("wheel", (e) => this.zoom(e), { passive: false });
    this.chart.addEventListener("mousedown", (e) => this.drag(e));
  }

  async show(on) {
    if (!on) return;
    try {
      const nodes = await this.api.get("/api/history/nodes");
      const names = nodes.map((n) => n.node);
      const chosen = this.nodeSel.value;
      this.nodeSel.innerHTML = names.map((n) => `<option value="${esc(n)}">${esc(n)}</option>`).join("");
      if (names.includes(chosen)) this.nodeSel.value = chosen;
      if (!names.length) {
        this.say("No rollups yet: the relay writes them as it compacts batches older than its --compact-after (60 s).");
        this.chart.replaceChildren();
        this.table.innerHTML = "";
        return;
      }
    } catch (err) {
      this.say(`History unavailable: ${err.message}`);
      return;
    }
    await this.load();
  }

  say(text) {
    this.note.textContent = text;
  }

  span() {
    if (this.window) return this.window;
    const now = Date.now() * 1e6;
    return [now - Number(this.spanSel.value) * 1e9, now];
  }

  async load() {
    const node = this.nodeSel.value;
    if (!node) return;
    const [since, until] = this.span();
    const seq = ++this.seq;
    let doc;
    try {
      doc = await this.api.get(`/api/history?node=${q(node)}&since=${Math.round((until - since) / 1e9)}s` +
                               `&until_ns=${BigInt(Math.round(until))}`);
    } catch (err) {
      if (seq === this.seq) this.say(`History of ${node} unavailable: ${err.message}`);
      return;
    }
    if (seq !== this.seq) return; // a newer request went out meanwhile
    this.doc = doc;
    this.draw(doc.history, since, until);
    this.summary(doc.summary);
    const width = doc.history.width_ns === 60e9 ? "minute" : "hour";
    this.say(`${node}: a point per ${width} · p99 solid, p50 dashed · a break in a line: no frames then · ` +
             `${stamp(since)} to ${stamp(until)}`);
  }

  width() {
    return Math.max(300, Math.round(this.chart.clientWidth || 1000));
  }

  draw(h, since, until) {
    const W = this.width();
    const lines = [["frame", h.frame], ...Object.entries(h.stages)];
    const top = Math.max(1e-3, ...lines.flatMap(([, pts]) => pts.map((p) => p.p99_ms)));
    const x = (t) => LEFT + ((t - since) / (until - since)) * (W - LEFT - RIGHT);
    const y = (ms) => TOP + (1 - ms / top) * (H - TOP - BOTTOM);
    const svg = [];
    for (let k = 0; k <= 4; k++) {
      const ms = (top * k) / 4;
      svg.push(`<line class="grid" x1="${LEFT}" x2="${W - RIGHT}" y1="${y(ms)}" y2="${y(ms)}"/>`,
               `<text class="axis" x="${LEFT - 4}" y="${y(ms) + 4}" text-anchor="end">${ms.toFixed(ms < 10 ? 1 : 0)} ms</text>`);
    }
    for (let k = 0; k <= 4; k++) {
      const t = since + ((until - since) * k) / 4;
      svg.push(`<text class="axis" x="${x(t)}" y="${H - 6}" text-anchor="middle">${stamp(t)}</text>`);
    }
    lines.forEach(([name, pts], i) => {
      const colour = name === "frame" ? "#263238" : COLOURS[i % COLOURS.length];
      for (const [key, dash] of [["p99_ms", ""], ["p50_ms", ` stroke-dasharray="4 3"`]]) {
        svg.push(`<path class="history-line" data-stage="${esc(name)}" data-q="${key}" stroke="${colour}"${dash} ` +
                 `d="${pathOf(pts, key, h.width_ns, x, y)}"><title>${esc(name)} ${key.slice(0, 3)}</title></path>`);
      }
    });
    this.chart.setAttribute("viewBox", `0 0 ${W} ${H}`);
    this.chart.innerHTML = svg.join("");
    this.legend(lines);
  }

  legend(lines) {
    const el = this.chart.parentElement.querySelector(".history-legend");
    el.innerHTML = lines.map(([name], i) => `<span class="legend-item"><span class="swatch" style="background:` +
      `${name === "frame" ? "#263238" : COLOURS[i % COLOURS.length]}"></span>${esc(name === "frame" ? "frame (end to end)" : name)}</span>`).join("");
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
      `p50, p90, p99 from the sketch, within ${s.relative_error * 100} % of the value.</p>`;
  }

  zoom(e) {
    e.preventDefault();
    const [since, until] = this.span();
    const box = this.chart.getBoundingClientRect();
    const W = this.width();
    const frac = Math.min(1, Math.max(0, ((e.clientX - box.left) / box.width * W - LEFT) / (W - LEFT - RIGHT)));
    const at = since + frac * (until - since);
    const span = Math.min(MAX_SPAN_NS, Math.max(MIN_SPAN_NS, (until - since) * (e.deltaY > 0 ? 1.5 : 1 / 1.5)));
    this.window = [at - frac * span, at + (1 - frac) * span];
    this.load();
  }

  drag(e) {
    const [since, until] = this.span();
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

function stamp(ns) {
  const d = new Date(ns / 1e6);
  return d.toISOString().slice(0, 16).replace("T", " ");
}
