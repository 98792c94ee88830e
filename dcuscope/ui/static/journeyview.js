// Journeys view: frames that went from one DCU's pipeline to another's (RTP, shared memory),
// followed across them on the relay's clock (GET /api/journeys, polled while live data shows).
// Per hop a line: its delays, the frames it lost, its clock error. Below, one bar per journey,
// oldest at the top, from the frame's first origin to its end on the last DCU: a segment per DCU
// in that DCU's colour and a hatched segment per hop between them, with the hop's clock error bar
// at its end. The same journeys feed `hops`, a row of the Stage view: a lane per hop, a bar per
// frame from its sending to its arrival.

import { PALETTE } from "./colours.js";
import { esc } from "./panels.js";
import { NodeStore } from "./store.js";
import { formatDelay } from "./timefmt.js";

export const HOPS_ROW = "⇄ hops";
const HOP_FRAMES = 2000;

const POLL_MS = 1000;
const JOURNEYS = 40;
const ROW = 14;
const GAP = 4;
const LABEL = 150;
const RIGHT_PAD = 16;
const TOP = 18;
const SVG_NS = "http://www.w3.org/2000/svg";
const HOP_COLOUR = "#455a64";

export class JourneyView {
  constructor(section, api) {
    this.api = api;
    this.hopList = section.querySelector("#journeys-hops");
    this.svg = section.querySelector("#journeys-chart");
    this.note = section.querySelector("#journeys-note");
    this.legend = section.querySelector("#journeys-legend");
    this.timer = null;
    this.shown = false;
    this.colours = new Map(); // DCU -> its colour, in order of appearance
    this.data = null;
    this.error = null;
    this.last = { journeys: 0, hops: 0, message: "" };
    this.hops = new NodeStore(HOPS_ROW, [], HOP_FRAMES); // the Stage view's row
  }

  /** Poll the relay while live data shows (`on`), for this tab and the Stage view's hop row. */
  follow(on) {
    clearInterval(this.timer);
    this.timer = null;
    if (!on) return;
    this.poll();
    this.timer = setInterval(() => this.poll(), POLL_MS);
  }

  show(on) {
    this.shown = on;
    if (on) this.draw(this.error);
  }

  async poll() {
    try {
      this.data = await this.api.get(`/api/journeys?limit=${JOURNEYS}&hops=${HOP_FRAMES}`);
      this.error = null;
      this.hops.ingest(hopBlock(this.data));
    } catch (err) {
      this.data = null;
      this.error = err.message;
    }
    if (this.shown) this.draw(this.error);
  }

  colourOf(node) {
    if (!this.colours.has(node)) this.colours.set(node, PALETTE[this.colours.size % PALETTE.length]);
    return this.colours.get(node);
  }

  draw(error) {
    const d = this.data;
    const hops = Object.entries(d?.hops ?? {});
    const frames = d?.frames ?? [];
    const message = error ?? (hops.length ? "" : "No frame has gone from one DCU's pipeline to another's yet: " +
      "trace both ends (an RTP sender and its receiver, a shmsink and its shmsrc) with the dcuscope tracer.");
    this.note.textContent = message;
    this.note.classList.toggle("field-msg", !!error);
    this.hopList.innerHTML = hops.map(([name, h]) => `<li><b>${esc(name)}</b>: p50 ${formatDelay(h.p50_ms)}, ` +
      `p95 ${formatDelay(h.p95_ms)}, ${h.count} frames, ${h.lost} lost · clock error ` +
      `${h.clock_error_ms === null ? "unknown (no estimate yet)" : "± " + formatDelay(h.clock_error_ms)}</li>`).join("") +
      Object.entries(d?.paths ?? {}).map(([path, p]) => `<li>journey <b>${esc(path)}</b>: p50 ` +
        `${formatDelay(p.p50_ms)}, p95 ${formatDelay(p.p95_ms)}, max ${formatDelay(p.max_ms)} (${p.count} frames)</li>`).join("");
    this.last = { journeys: frames.length, hops: hops.length, message };
    this.drawBars(frames);
    const legend = [...this.colours.entries()].map(([node, colour]) =>
      `<span class="legend-item"><span class="swatch" style="background:${colour}"></span>on ${esc(node)}</span>`);
    if (hops.length) legend.push('<span class="legend-item"><span class="swatch hop-swatch"></span>a hop between two DCUs</span>');
    const html = legend.join("");
    if (this.legend.innerHTML !== html) this.legend.innerHTML = html;
  }

  drawBars(frames) {
    const svg = this.svg;
    while (svg.firstChild) svg.removeChild(svg.firstChild);
    const W = Math.max(320, svg.parentElement.clientWidth - 2);
    const H = TOP + frames.length * (ROW + GAP) + 8;
    svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
    svg.style.height = `${H}px`;
    if (!frames.length) return;
    const longest = Math.max(...frames.map((f) => f.total_ms), 0.001);
    const kx = (W - LABEL - RIGHT_PAD) / longest;
    const add = (tag, attrs, parent = svg) => {
      const el = document.createElementNS(SVG_NS, tag);
      for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
      parent.appendChild(el);
      return el;
    };
    const defs = add("defs", {});
    const hatch = add("pattern", { id: "hop-hatch", width: 6, height: 6, patternUnits: "userSpaceOnUse",
      patternTransform: "rotate(45)" }, defs);
    add("rect", { width: 6, height: 6, fill: "#eceff1" }, hatch);
    add("rect", { width: 3, height: 6, fill: HOP_COLOUR }, hatch);
    add("text", { x: LABEL, y: 12, class: "axis" }).textContent = `0 … ${formatDelay(longest)} from each frame's first origin`;
    frames.forEach((f, row) => {
      const y = TOP + row * (ROW + GAP);
      const bar = add("g", { class: "journey", "data-nodes": f.nodes.join(" → "), "data-total-ns": f.total_ns });
      add("text", { x: LABEL - 6, y: y + ROW - 3, "text-anchor": "end", class: "axis" }, bar).textContent =
        `${f.nodes.join(" → ")} ${formatDelay(f.total_ms)}`;
      for (const p of f.parts) {
        // A hop can be a hair below zero on one machine (the receiver had the frame before the
        // sender's call returned): drawn over the span it covers, at least a pixel wide.
        const ms = p.ns / 1e6;
        const x = LABEL + (Math.min(p.at_ns, p.at_ns + p.ns) / 1e6) * kx;
        const w = Math.max(1, Math.abs(ms) * kx);
        const seg = add("rect", { x, y, width: w, height: ROW, class: `part part-${p.kind}`,
          fill: p.kind === "hop" ? "url(#hop-hatch)" : this.colourOf(p.name), "data-name": p.name,
          "data-at-ns": p.at_ns, "data-ns": p.ns }, bar);
        const error = p.clock_error_ns === undefined ? "" : p.clock_error_ns === null
          ? " (clock error unknown)" : ` ± ${formatDelay(p.clock_error_ns / 1e6)} (both DCUs' clocks)`;
        add("title", {}, seg).textContent = `${p.kind === "hop" ? "hop " : "on "}${p.name}: ${formatDelay(ms)}${error}`;
        if (p.kind === "hop" && p.clock_error_ns) {
          const e = (p.clock_error_ns / 1e6) * kx;
          add("line", { x1: x + w - e, x2: x + w + e, y1: y + ROW / 2, y2: y + ROW / 2, class: "error-bar" }, bar);
        }
      }
    });
  }
}

/**
 * The Stage view's hop row as a block for NodeStore.ingest: a lane per hop, and per frame that
 * crossed (GET /api/journeys's `crossed`, relay clock, ns) a bar from its sending to its arrival.
 */
export function hopBlock(data) {
  const stages = Object.keys(data.hops ?? {});
  const frames = (data.crossed ?? []).map((c) => {
    const s = stages.indexOf(c.hop);
    const enter = stages.map((_, i) => (i === s ? c.sent_ns : null));
    const exit = stages.map((_, i) => (i === s ? c.arrived_ns : null));
    const ms = (c.arrived_ns - c.sent_ns) / 1e6;
    return { n: c.n, source: 0, frame: c.n, origin: c.sent_ns, end: c.arrived_ns, enter, exit, delay_ms: ms,
      stage_delay_ms: stages.map((_, i) => (i === s ? ms : NaN)), clock_ns: 0,
      clock_uncertainty_ns: c.clock_error_ns };
  });
  return { run: `hops:${stages.join(",")}`, stages, has_exit: stages.map(() => true), clock: "estimate", frames };
}
