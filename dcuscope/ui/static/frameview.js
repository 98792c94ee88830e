// Frame view (the paper's Figure 14): per DCU one horizontal bar per frame, as long as the
// frame's end-to-end delay, a red vertical limit line, bars over the limit in deep red, and the
// count and share of frames over the limit. A DCU's limit is the page's, else the relay's
// --frame-limit for it, else none: then no frame is judged, and the counts say how to set one.

import { LIMIT_LINE, OVER_LIMIT, UNDER_LIMIT } from "./colours.js";
import { esc } from "./panels.js";
import { delayTicks, formatClock, formatClockPrecise, formatDelay, formatTick, niceCeil } from "./timefmt.js";

const GUTTER = 96;
const TOP = 18;
const AXIS_H = 22;
const RIGHT_PAD = 12;
const CANVAS_H = 340;
const MAX_PITCH = 14; // px per frame at most (few frames)
const GAP_FROM = 2; // px per frame from which bars are drawn a pixel apart

export const RECEIVED_TITLE = "The frames of this DCU the page received: the relay's most recent ones (a few thousand "
  + "at most) when the DCU was opened here, then every new one; at most the last 1,048,576. So each DCU counts from "
  + "its own instant: a DCU with more frames a second has fewer seconds in the relay's few thousand.";

/**
 * Where a DCU's counts start, and why there: its run's first frame, or the oldest frame the relay
 * still kept of it (the relay keeps each run's newest few thousand frames) when the page opened it.
 */
export function sinceText(c) {
  if (c.since === null || c.since === undefined) return "";
  const at = ` since ${esc(formatClock(c.since).slice(0, 8))}`;
  if (!c.firstN || c.firstN <= 1) return `${at} (its run's start)`;
  const before = fmtInt(c.firstN - 1);
  return `${at} <span class="since-why" title="the relay keeps each run's newest few thousand frames: `
    + `${before} earlier frames of this run had left it when the DCU was opened here (its stored session holds them)">`
    + `(the relay's oldest kept: ${before} before it not received)</span>`;
}

const fmtInt = (n) => n.toLocaleString("en-US");
const pct = (a, b) => (b ? `${((100 * a) / b).toFixed(1)}%` : "–");

export class FrameView {
  /**
   * @param model {stores(): NodeStore[], limit(node): ms | null (the DCU's limit in force), chosenLimit(): ms | null
   *   (the page's), p99(node): ms | null, describe(node, source): string}
   */
  constructor(container, model) {
    this.container = container;
    this.model = model;
    this.panels = new Map();
    this.emptyEl = document.createElement("p");
    this.emptyEl.className = "muted frame-empty";
    this.last = { nodes: {}, xmax: 0, limit: null };
  }

  /** One panel (header with counters + canvas) per node, in node order. */
  sync() {
    const stores = this.model.stores();
    const names = new Set(stores.map((s) => s.node));
    for (const [node, panel] of this.panels) {
      if (!names.has(node)) {
        panel.el.remove();
        this.panels.delete(node);
      }
    }
    for (const store of stores) {
      if (this.panels.has(store.node)) continue;
      const el = document.createElement("div");
      el.className = "frame-panel";
      el.dataset.node = store.node;
      el.innerHTML = `<div class="frame-head"><b class="frame-node"></b> <span class="frame-counts"></span>
        <span class="frame-total muted" title="${esc(RECEIVED_TITLE)}"></span></div>
        <canvas class="frame-canvas"></canvas>`;
      el.querySelector(".frame-node").textContent = store.node;
      const canvas = el.querySelector("canvas");
      const panel = { el, canvas, ctx: canvas.getContext("2d", { alpha: false }), node: store.node, rows: null };
      this.panels.set(store.node, panel);
    }
    // Keep DOM order = node order.
    for (const store of stores) this.container.appendChild(this.panels.get(store.node).el);
    const empty = stores.length ? null : this.model.empty?.() ?? "Waiting for nodes.";
    if (this.emptyEl.textContent !== (empty ?? "")) this.emptyEl.textContent = empty ?? "";
    if (!empty) this.emptyEl.remove();
    else if (!this.emptyEl.isConnected) this.container.appendChild(this.emptyEl);
  }

  /** Draw the last `count` frames of every node that ended at or before `tEnd`. */
  draw(tEnd, count) {
    this.sync();
    const ranges = [];
    let maxDelay = 0;
    let maxLimit = 0;
    for (const store of this.model.stores()) {
      const hi = store.firstEndingBeyond(tEnd);
      const lo = Math.max(0, hi - count);
      for (let i = lo; i < hi; i++) maxDelay = Math.max(maxDelay, store.delay[store.slot(i)]);
      const limit = this.model.limit(store.node);
      if (limit !== null) maxLimit = Math.max(maxLimit, limit);
      ranges.push({ store, lo, hi, limit });
    }
    // One delay scale for every DCU, so their bars compare at a glance.
    const xmax = niceCeil(Math.max(maxLimit * 1.25, maxDelay * 1.05, 1));
    const nodes = {};
    for (const { store, lo, hi, limit } of ranges) {
      nodes[store.node] = this.drawPanel(this.panels.get(store.node), store, lo, hi, xmax, limit);
    }
    this.last = { nodes, xmax, limit: this.model.chosenLimit(), tEnd, count };
  }

  /** One DCU's bars; `limit` null: none, no frame judged. */
  drawPanel(panel, store, lo, hi, xmax, limit) {
    const { canvas, ctx } = panel;
    const dpr = window.devicePixelRatio || 1;
    const W = Math.max(240, canvas.parentElement.clientWidth - 2);
    if (panel.W !== W || panel.dpr !== dpr) {
      panel.W = W;
      panel.dpr = dpr;
      canvas.width = Math.round(W * dpr);
      canvas.height = Math.round(CANVAS_H * dpr);
      canvas.style.width = `${W}px`;
      canvas.style.height = `${CANVAS_H}px`;
    }
    const PW = W - GUTTER - RIGHT_PAD;
    const PH = CANVAS_H - TOP - AXIS_H;
    const kx = PW / xmax;
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#ffffff";
    ctx.fillRect(0, 0, W, CANVAS_H);

    const ticks = delayTicks(xmax, PW);
    ctx.font = "11px ui-monospace, SFMono-Regular, Menlo, monospace";
    ctx.textBaseline = "top";
    ctx.textAlign = "center";
    for (const v of ticks.values) {
      const x = Math.round(GUTTER + v * kx);
      ctx.fillStyle = "#eceff1";
      ctx.fillRect(x, TOP, 1, PH);
      ctx.fillStyle = "#455a64";
      ctx.fillText(formatTick(v), Math.min(x, W - 30), TOP + PH + 5);
    }

    const K = hi - lo;
    const judged = limit !== null;
    let over = 0;
    const under = new Path2D();
    const overPath = new Path2D();
    let rows;
    if (K > 0 && PH / K >= 1) {
      // A bar per frame, oldest at the top, a pixel apart where there is room.
      const pitch = Math.min(PH / K, MAX_PITCH);
      const h = pitch >= GAP_FROM ? pitch - 1 : pitch;
      rows = { pitch, lo, K, binned: false, bar: h };
      for (let i = 0; i < K; i++) {
        const d = store.delay[store.slot(lo + i)];
        const isOver = judged && d > limit;
        if (isOver) over++;
        (isOver ? overPath : under).rect(GUTTER, TOP + i * pitch, Math.max(1, d * kx), h);
      }
    } else if (K > 0) {
      // More frames than pixel rows: a row shows the slowest frame of its bin, so no frame over
      // the limit can hide behind a faster neighbour.
      rows = { pitch: PH / K, lo, K, binned: true, bar: 1 };
      if (judged) for (let i = 0; i < K; i++) if (store.delay[store.slot(lo + i)] > limit) over++;
      for (let r = 0; r < PH; r++) {
        const a = Math.floor((r * K) / PH);
        const b = Math.max(a + 1, Math.floor(((r + 1) * K) / PH));
        let d = 0;
        for (let i = a; i < b; i++) d = Math.max(d, store.delay[store.slot(lo + i)]);
        (judged && d > limit ? overPath : under).rect(GUTTER, TOP + r, Math.max(1, d * kx), 1);
      }
    }
    ctx.fillStyle = UNDER_LIMIT;
    ctx.fill(under);
    ctx.fillStyle = OVER_LIMIT;
    ctx.fill(overPath);
    panel.rows = rows ? { ...rows, PH } : null;

    // Origin times down the left side, so a spike can be found in the stage view.
    ctx.font = "10px ui-monospace, SFMono-Regular, Menlo, monospace";
    ctx.textAlign = "right";
    ctx.textBaseline = "middle";
    ctx.fillStyle = "#607d8b";
    if (rows) {
      const every = Math.max(1, Math.ceil(48 / Math.max(rows.pitch, PH / K)));
      for (let i = 0; i < K; i += every) {
        const y = TOP + (rows.binned ? (i * PH) / K : i * rows.pitch + rows.pitch / 2);
        if (y > TOP + PH - 6) break;
        ctx.fillText(formatClock(store.origin[store.slot(lo + i)]), GUTTER - 6, y);
      }
    } else {
      ctx.textAlign = "left";
      ctx.fillText("no frames yet", GUTTER + 8, TOP + 20);
    }

    if (judged) {
      const lx = Math.round(GUTTER + limit * kx);
      ctx.fillStyle = LIMIT_LINE;
      ctx.fillRect(lx - 1, TOP - 4, 2, PH + 4);
      ctx.font = "bold 11px system-ui, sans-serif";
      ctx.textBaseline = "top";
      ctx.textAlign = lx > W - 90 ? "right" : "left";
      ctx.fillText(`limit ${formatTick(limit)}`, lx + (lx > W - 90 ? -4 : 4), 2);
    }
    ctx.fillStyle = "#90a4ae";
    ctx.fillRect(GUTTER, TOP + PH, PW, 1);

    const ring = store.delays;
    const counts = { shown: K, overShown: over, received: ring.size, overReceived: ring.over, binned: !!rows?.binned,
      limit, pitch: rows?.pitch ?? null, bar: rows?.bar ?? null, since: ring.since, firstN: ring.firstN, wrapped: ring.wrapped };
    this.updateCounts(panel, counts, this.model.p99?.(store.node) ?? null);
    return counts;
  }

  /** The panel's two count lines: frames drawn, and every frame the page received (`p99`: a hint without a limit). */
  updateCounts(panel, c, p99) {
    const set = (cls, html) => {
      const el = panel.el.querySelector(cls);
      if (el._html !== html) {
        el._html = html;
        el.innerHTML = html;
      }
    };
    const n = `<span class="received">${fmtInt(c.received)}</span>`;
    const since = sinceText(c);
    const received = c.wrapped ? `the last ${n} frames received` : `${n} frames received${since}`;
    if (c.limit === null) {
      const hint = p99 === null ? "" : ` (its p99: ${esc(formatDelay(p99))})`;
      set(".frame-counts", `<span class="shown-count">${fmtInt(c.shown)}</span> shown · no limit set: type one above${hint}`);
      set(".frame-total", received);
      return;
    }
    set(".frame-counts", `<span class="over-count">${fmtInt(c.overShown)}</span> of <span class="shown-count">`
      + `${fmtInt(c.shown)}</span> shown over <span class="limit-text">${esc(formatTick(c.limit))}</span>`
      + ` (<span class="over-share">${pct(c.overShown, c.shown)}</span>)`);
    set(".frame-total", `<span class="over-total">${fmtInt(c.overReceived)}</span> of ${c.wrapped ? "" : "the "}${received}`
      + ` were over it (<span class="over-total-share">${pct(c.overReceived, c.received)}</span>)`);
  }

  /** The frame under (x, y) of a panel's canvas, or null. */
  hit(node, x, y) {
    const panel = this.panels.get(node);
    const store = this.model.stores().find((s) => s.node === node);
    if (!panel || !panel.rows || !store || x < GUTTER) return null;
    const { pitch, lo, K, binned, PH } = panel.rows;
    const r = y - TOP;
    if (r < 0 || r >= (binned ? PH : K * pitch)) return null;
    let i;
    if (binned) {
      const a = Math.floor((Math.floor(r) * K) / PH);
      const b = Math.max(a + 1, Math.floor(((Math.floor(r) + 1) * K) / PH));
      i = a;
      for (let j = a; j < b; j++) if (store.delay[store.slot(lo + j)] > store.delay[store.slot(lo + i)]) i = j;
    } else {
      i = Math.floor(r / pitch);
    }
    const p = store.slot(lo + i);
    const stages = [];
    for (let s = 0; s < store.S; s++) {
      const d = store.stageDelay[p * store.S + s];
      if (d === d) stages.push([store.stages[s], d]);
    }
    return { node, source: store.source[p], frame: store.frame[p], origin: store.origin[p], delay: store.delay[p], stages };
  }

  static describeHit(h, describe, limit) {
    const lines = [
      `${h.node} · source ${h.source} (${describe(h.node, h.source)}) · frame ${h.frame}`,
      `origin ${formatClockPrecise(h.origin)}`,
      `end-to-end delay ${formatDelay(h.delay)}${limit !== null && h.delay > limit ? "  (over the limit)" : ""}`,
    ];
    if (h.stages.length) lines.push(h.stages.map(([s, d]) => `${s} ${formatDelay(d)}`).join(" · "));
    return lines;
  }
}
