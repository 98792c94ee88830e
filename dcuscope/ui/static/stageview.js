// Stage view (the paper's Figure 13): one row per DCU, or per DCU and source; in a row one lane
// per stage, and for every frame a bar from its enter to its exit at that stage.
//
// Times are the relay's clock (each node's correction applied), or with `model.raw()` each node's
// own clock: raw = corrected + the offset the relay subtracted at the frame's origin. At the start
// of each row a band as wide as twice the node's clock uncertainty (± U, at the current zoom) says
// how far any bar of that row may truly lie from where it is drawn, relative to other rows.

import { tint } from "./colours.js";
import { columnCoverage, Intervals, serviceStart } from "./coverage.js";
import { clockTicks, formatClock, formatClockPrecise, formatDelay, formatOffsetBound } from "./timefmt.js";

export const GUTTER = 150;
const AXIS_H = 30;
const RIGHT_PAD = 10;
const LANE_H = 10;
const LANE_GAP = 2;
const ROW_PAD = 6;
const HIT_PX = 3;
const LANE_FONT = "9px system-ui, sans-serif";
const LANE_LABEL_MAX = 48; // px: longer stage names are cut, leaving the row's name some room
const LABEL_GAP = 6; // px between a row's name and its stage names
const BAND_FILL = "rgba(255, 152, 0, 0.35)"; // the clock uncertainty band: translucent, bars show through
const BAND_TEXT = "#e65100";
const HEADER_MIN_H = 48;
const HEADER_SPLIT_MIN_H = 56;

/** "± 120 µs": a clock bound in ms as the band's label reads it. */
export function formatBound(ms) {
  const us = ms * 1000;
  return `± ${us >= 9.95 ? Math.round(us).toLocaleString("en-US") : us.toFixed(1)} µs`;
}

/** `text` cut with an ellipsis to fit `width` px in ctx's font: its start kept, or its end. */
export function fitText(ctx, text, width, keepEnd = false) {
  if (ctx.measureText(text).width <= width) return text;
  const cut = (k) => (keepEnd ? `…${text.slice(text.length - k)}` : `${text.slice(0, k)}…`);
  let lo = 0;
  let hi = text.length - 1;
  while (lo < hi) {
    const mid = (lo + hi + 1) >> 1;
    if (ctx.measureText(cut(mid)).width <= width) lo = mid;
    else hi = mid - 1;
  }
  return lo > 0 ? cut(lo) : "";
}

/**
 * Whether the bar [px0, px1) joins the run [rx0, rx1) drawn so far in its lane. Frames come in
 * arrival order, not in order of their time at a stage, so a bar may lie left of the run: it
 * joins only where the two overlap (or touch, when one is too narrow to show a 1 px seam), so
 * that a run never covers pixels where no frame was.
 */
export function joins(rx0, rx1, px0, px1) {
  const overlap = Math.min(px1, rx1) - Math.max(px0, rx0);
  return overlap > 1 || (overlap >= 0 && (px1 - px0 <= 2 || rx1 - rx0 <= 2));
}

const known = (ms) => (ms === ms ? formatDelay(ms) : "–");

/** `a` twice as long, its content kept. */
function grown(a) {
  const b = new a.constructor(a.length * 2);
  b.set(a);
  return b;
}

/**
 * The whole bars of one lane, joined into runs as they come (fewer rectangles to fill), each run
 * light, with the solid spans of its bars' service on top.
 */
class Runs {
  constructor(y, pending) {
    this.y = y;
    this.pend = pending; // solid spans [a, b) of the run being gathered, clipped at its end when drawn
    this.np = 0;
    this.rx0 = -1;
    this.rx1 = -1;
    this.light = new Path2D();
    this.solid = new Path2D();
    this.count = 0;
    this.best = null;
  }

  /** A bar [px0, px1) whose solid part is [ps, px1). */
  add(px0, px1, ps) {
    if (this.rx0 >= 0 && joins(this.rx0, this.rx1, px0, px1)) {
      this.rx0 = Math.min(this.rx0, px0);
      this.rx1 = Math.max(this.rx1, px1);
    } else {
      this.flush();
      this.rx0 = px0;
      this.rx1 = px1;
    }
    if (ps < px1) {
      if (this.np + 2 > this.pend.length) this.pend = grown(this.pend);
      this.pend[this.np++] = ps;
      this.pend[this.np++] = px1;
    }
  }

  flush() {
    const { rx0, rx1, y, pend } = this;
    if (rx0 < 0) return;
    // A 1 px seam between touching bars wide enough to show it keeps frames apart.
    const w = rx1 - rx0 >= 4 ? rx1 - rx0 - 1 : rx1 - rx0;
    this.light.rect(rx0, y, w, LANE_H);
    for (let q = 0; q < this.np; q += 2) {
      const b = Math.min(pend[q + 1], rx0 + w);
      if (b > pend[q]) this.solid.rect(pend[q], y, b - pend[q], LANE_H);
    }
    this.np = 0;
    this.rx0 = -1;
    this.count++;
    if (this.best === null || w > this.best.w) this.best = { x: rx0, y, w, h: LANE_H };
  }
}

export class StageView {
  /**
   * @param canvas the <canvas> to draw on
   * @param model {stores(): NodeStore[] sorted by node, colours: StageColours,
   *               expanded(node): bool, describe(node, source): string,
   *               raw(): bool (node timestamps as they came, not corrected),
   *               empty(): what to say when there is no row (null: that no node has come yet)}
   */
  constructor(canvas, model) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d", { alpha: false });
    this.model = model;
    this.rows = [];
    this.t0 = 0;
    this.t1 = 1;
    this.scratch = new Int32Array(1024);
    this.pending = new Int32Array(1024);
    this.narrow = { wait: new Intervals(), service: new Intervals() };
    this.columns = new Float32Array(0);
    this.shade = document.createElement("canvas"); // one row: a lane's shaded columns
    this.shade.height = 1;
    this.shadeCtx = this.shade.getContext("2d");
    this.shadeRow = null;
    this.pale = new Map(); // stage colour -> its wait tint
    this.last = { bars: {}, runs: 0, samples: {}, rows: [], bands: {}, raw: false };
    this.raw = false;
  }

  /** ms to add to frame `p`'s corrected times to draw it: its clock offset in raw mode, else 0. */
  shift(store, p) {
    return this.raw ? store.clock[p] : 0;
  }

  get plotX() {
    return GUTTER;
  }

  get plotWidth() {
    return Math.max(50, this.cssWidth - GUTTER - RIGHT_PAD);
  }

  /** Rows and their lanes; resizes the canvas when its content height changed. */
  layout() {
    const rows = [];
    let y = AXIS_H;
    for (const store of this.model.stores()) {
      const lanes = store.lanes;
      const h = Math.max(1, lanes.length) * (LANE_H + LANE_GAP) - LANE_GAP + 2 * ROW_PAD;
      const split = this.model.expanded(store.node) && store.sources.length > 0;
      // A header row holds its name, "all sources" when split, and its clock label.
      const hh = Math.max(h, split ? HEADER_SPLIT_MIN_H : HEADER_MIN_H);
      rows.push({ store, node: store.node, source: null, y, h: hh, lanes, header: true, split });
      y += hh;
      if (split) {
        for (const source of store.sources) {
          rows.push({ store, node: store.node, source, y, h, lanes, header: false });
          y += h;
        }
      }
    }
    this.rows = rows;
    const cssHeight = Math.max(y + 8, 120);
    const cssWidth = Math.max(300, this.canvas.parentElement.clientWidth);
    const dpr = window.devicePixelRatio || 1;
    if (cssWidth !== this.cssWidth || cssHeight !== this.cssHeight || dpr !== this.dpr) {
      this.cssWidth = cssWidth;
      this.cssHeight = cssHeight;
      this.dpr = dpr;
      this.canvas.width = Math.round(cssWidth * dpr);
      this.canvas.height = Math.round(cssHeight * dpr);
      this.canvas.style.width = `${cssWidth}px`;
      this.canvas.style.height = `${cssHeight}px`;
    }
  }

  /** Draw the window [t0, t1] (ms since the epoch, relay clock). */
  draw(t0, t1) {
    this.layout();
    this.t0 = t0;
    this.t1 = t1;
    this.raw = !!this.model.raw?.();
    const ctx = this.ctx;
    const W = this.cssWidth;
    const H = this.cssHeight;
    const X = GUTTER;
    const PW = this.plotWidth;
    const k = PW / (t1 - t0);
    ctx.setTransform(this.dpr, 0, 0, this.dpr, 0, 0);
    ctx.fillStyle = "#ffffff";
    ctx.fillRect(0, 0, W, H);

    // Row backgrounds, then the time grid over them, then bars on top.
    this.rows.forEach((row, i) => {
      ctx.fillStyle = row.header ? (i % 2 ? "#f4f6f8" : "#fafbfc") : "#fdfdf6";
      ctx.fillRect(0, row.y, W, row.h);
    });
    const ticks = clockTicks(t0, t1, PW);
    ctx.fillStyle = "#eceff1";
    for (const t of ticks.minor) ctx.fillRect(Math.round(X + (t - t0) * k), AXIS_H - 4, 1, H - AXIS_H + 4);
    ctx.fillStyle = "#cfd8dc";
    for (const t of ticks.major) ctx.fillRect(Math.round(X + (t - t0) * k), AXIS_H - 8, 1, H - AXIS_H + 8);
    ctx.fillStyle = "#263238";
    ctx.font = "11px ui-monospace, SFMono-Regular, Menlo, monospace";
    ctx.textBaseline = "top";
    ctx.textAlign = "center";
    // Edge labels give the window's exact bounds; tick labels that would overlap them are left out.
    const half = ctx.measureText("00:00:00.000").width / 2 + 6;
    for (const t of ticks.major) {
      const x = X + (t - t0) * k;
      if (x > X + 3 * half && x < X + PW - 3 * half) ctx.fillText(formatClock(t), x, 6);
    }
    ctx.textAlign = "left";
    ctx.fillText(formatClock(t0), X, 6);
    ctx.textAlign = "right";
    ctx.fillText(formatClock(t1), X + PW, 6);

    const bars = {};
    const samples = {};
    const bySource = {};
    const lanes = {};
    const bands = {};
    let runs = 0;
    for (const row of this.rows) {
      const store = row.store;
      this.drawLabel(row);
      if (!store.size) continue;
      const visible = this.visible(store, row.source, t0, t1);
      const perNode = (bars[row.node] ??= {});
      row.lanes.forEach((s, li) => {
        const stage = store.stages[s];
        const lane = this.drawLane(store, visible, s, row.y + ROW_PAD + li * (LANE_H + LANE_GAP));
        runs += lane.runs;
        if (row.header) {
          perNode[stage] = lane.drawn;
          (lanes[row.node] ??= {})[stage] = { bars: lane.bars, narrow: lane.narrow, service: lane.service, wait: lane.wait };
          if (lane.best) (samples[row.node] ??= {})[stage] = lane.best;
        } else {
          ((bySource[row.node] ??= {})[row.source] ??= {})[stage] = lane.drawn;
        }
      });
      const band = this.drawBand(row, visible);
      if (row.header) bands[row.node] = band;
    }
    if (!this.rows.length) {
      ctx.fillStyle = "#607d8b";
      ctx.font = "14px system-ui, sans-serif";
      ctx.textAlign = "left";
      ctx.fillText(this.model.empty?.() ?? "Waiting for nodes: dcuscope run CONFIG --probes --relay URL --node NAME", X, AXIS_H + 20);
    }
    this.last = {
      bars, bySource, runs, samples, lanes, bands, raw: this.raw, window: [t0, t1],
      rows: this.rows.map((r) => ({ node: r.node, source: r.source, y: r.y, h: r.h, lanes: r.lanes.map((s) => r.store.stages[s]) })),
    };
  }

  /**
   * One lane: every frame's bar from its enter to its exit at stage `s`, its wait light and its
   * service solid (service comes last: the stage waits, then works, then the frame exits). Bars
   * narrower than a pixel, and service parts narrower than a pixel, are not drawn at a minimum
   * width but as the share of each pixel column they cover (coverage.js).
   * Returns what was drawn: frames, whole bars, narrow ones, covered columns (px), the widest run.
   */
  drawLane(store, visible, s, y) {
    const { t0, t1 } = this;
    const k = this.plotWidth / (t1 - t0);
    const S = store.S;
    const { wait, service } = this.narrow;
    wait.clear();
    service.clear();
    const runs = new Runs(y, this.pending);
    const out = { drawn: 0, bars: 0, narrow: 0, runs: 0, best: null, service: 0, wait: 0 };
    for (let j = 0; j < visible.length; j++) {
      const p = store.slot(visible[j]);
      const b = p * S + s;
      const sh = this.shift(store, p);
      const a = store.enter[b] + sh;
      const e = store.exit[b] + sh;
      if (!(e >= t0 && a <= t1)) continue; // NaN fails both: no bar
      out.drawn++;
      const ca = Math.max(a, t0);
      const ce = Math.min(e, t1);
      const cs = Math.max(ca, Math.min(ce, serviceStart(a, e, store.stageService[b])));
      if ((ce - ca) * k < 1) {
        out.narrow++;
        wait.add(ca, cs);
        service.add(cs, ce);
        continue;
      }
      out.bars++;
      const px0 = Math.floor(GUTTER + (ca - t0) * k);
      const px1 = Math.max(px0 + 1, Math.round(GUTTER + (ce - t0) * k));
      let ps = px1; // no solid part drawn whole: a service under a pixel is shaded as narrow bars are
      if ((ce - cs) * k < 1) service.add(cs, ce);
      else ps = Math.max(px0, Math.min(px1, Math.round(GUTTER + (cs - t0) * k)));
      runs.add(px0, px1, ps);
    }
    runs.flush();
    this.pending = runs.pend;
    out.runs = runs.count;
    out.best = runs.best;
    this.fillLane(store.stages[s], y, runs.light, runs.solid, out);
    return out;
  }

  /** Paint a lane: light bars, narrow waits, solid bars, narrow services, in that order. */
  fillLane(stage, y, light, solid, out) {
    const ctx = this.ctx;
    const colour = this.model.colours.get(stage);
    const pale = this.pale.get(colour) ?? this.pale.set(colour, tint(colour)).get(colour);
    ctx.fillStyle = pale;
    ctx.fill(light);
    const waits = this.fillCoverage(this.narrow.wait, y, pale);
    ctx.fillStyle = colour;
    ctx.fill(solid);
    const services = this.fillCoverage(this.narrow.service, y, colour);
    out.wait = waits.sum;
    out.service = services.sum;
    // No whole bar to point at (tests hover the widest): the most covered column.
    const x = services.best ?? waits.best;
    if (out.best === null && x !== null) out.best = { x, y, w: 1, h: LANE_H };
  }

  /**
   * Columns shaded by the share of their time `iv` covers, in `colour`: the covered sum (px) and
   * the most covered column's x (null: none). The shades go as one row of pixels, stretched to
   * the lane's height: one image per lane, not a fill per column.
   */
  fillCoverage(iv, y, colour) {
    if (!iv.n) return { sum: 0, best: null };
    const PW = this.plotWidth;
    if (this.columns.length !== PW) {
      this.columns = new Float32Array(PW);
      this.shade.width = PW;
      this.shadeRow = this.shadeCtx.createImageData(PW, 1);
    }
    const cov = columnCoverage(iv, this.t0, this.t1, PW, this.columns);
    const v = parseInt(colour.slice(1), 16);
    const px = this.shadeRow.data;
    let sum = 0;
    let top = 0;
    let best = null;
    for (let c = 0; c < PW; c++) {
      px[4 * c] = v >> 16;
      px[4 * c + 1] = (v >> 8) & 255;
      px[4 * c + 2] = v & 255;
      // Any share above 0 shows, however faint.
      px[4 * c + 3] = cov[c] > 0 ? Math.max(1, Math.round(cov[c] * 255)) : 0;
      sum += cov[c];
      if (cov[c] > top) {
        top = cov[c];
        best = GUTTER + c;
      }
    }
    this.shadeCtx.putImageData(this.shadeRow, 0, 0);
    this.ctx.imageSmoothingEnabled = false;
    this.ctx.drawImage(this.shade, 0, 0, PW, 1, GUTTER, y, PW, LANE_H);
    return { sum, best };
  }

  /**
   * The row's clock band: from the plot's start edge, 2U wide on the time axis (± U, U the largest
   * bound of the frames drawn, or of the newest frame when none is), over the row's height, drawn
   * over the bars (translucent); its label "± N µs" in a header row's gutter. None in raw mode,
   * whose label reads "raw clock", nor where the relay has no estimate. Returns what was drawn.
   */
  drawBand(row, visible) {
    const store = row.store;
    let u = -Infinity;
    for (let j = 0; j < visible.length; j++) u = Math.max(u, store.clockBound[store.slot(visible[j])]);
    if (!(u >= 0)) u = store.size ? store.clockBound[store.slot(store.size - 1)] : NaN;
    const known = !["none", "ignored"].includes(store.clockApplied) && u >= 0;
    const label = this.raw ? "raw clock" : known ? formatBound(u) : "no clock estimate";
    const k = this.plotWidth / (this.t1 - this.t0);
    const w = this.raw || !known ? 0 : Math.min(this.plotWidth, 2 * u * k);
    const ctx = this.ctx;
    if (w > 0) {
      ctx.fillStyle = BAND_FILL;
      ctx.fillRect(GUTTER, row.y, w, row.h);
    }
    if (row.header) {
      ctx.font = "10px system-ui, sans-serif";
      ctx.textAlign = "left";
      ctx.textBaseline = "middle";
      ctx.fillStyle = BAND_TEXT;
      const y = row.y + Math.min(row.h / 2, 16) + (row.split ? 30 : 15);
      ctx.fillText(fitText(ctx, label, this.labelRoom(row) - 8), 8, y);
    }
    return { x: GUTTER, w, uncertaintyMs: u, label, applied: store.clockApplied };
  }

  /** Room (px from the left) a row's names have before its stage names. */
  labelRoom(row) {
    const ctx = this.ctx;
    ctx.font = LANE_FONT;
    const widest = Math.max(0, ...row.lanes.map((s) => ctx.measureText(fitText(ctx, row.store.stages[s], LANE_LABEL_MAX)).width));
    return GUTTER - 6 - widest - LABEL_GAP;
  }

  /**
   * A row's gutter: its name (node, or source and its description) on the left, its lanes'
   * stage names right-aligned against the plot. The names are cut to the room the stage
   * names leave them, so the two never overlap, however long a node or source name is.
   */
  drawLabel(row) {
    const ctx = this.ctx;
    ctx.textBaseline = "middle";
    ctx.font = LANE_FONT;
    const lanes = row.lanes.map((s) => fitText(ctx, row.store.stages[s], LANE_LABEL_MAX));
    const laneLeft = GUTTER - 6 - Math.max(0, ...lanes.map((t) => ctx.measureText(t).width));
    const name = (text, x, y, font, keepEnd = false) => {
      ctx.font = font;
      ctx.fillText(fitText(ctx, text, laneLeft - LABEL_GAP - x, keepEnd), x, y);
    };
    ctx.textAlign = "left";
    ctx.fillStyle = "#263238";
    if (row.header) {
      const mark = row.store.sources.length > 1 ? (row.split ? "▾ " : "▸ ") : "";
      name(mark + row.node, 8, row.y + Math.min(row.h / 2, 16), "bold 13px system-ui, sans-serif");
      if (row.split) {
        ctx.fillStyle = "#607d8b";
        name("all sources", 22, row.y + Math.min(row.h / 2, 16) + 15, "11px system-ui, sans-serif");
      }
    } else {
      name(`source ${row.source}`, 22, row.y + 14, "12px system-ui, sans-serif");
      ctx.fillStyle = "#607d8b";
      // A path or URI: its end (the file name) tells sources apart.
      name(this.model.describe(row.node, row.source), 22, row.y + 28, "10px system-ui, sans-serif", true);
    }
    ctx.font = LANE_FONT;
    ctx.textAlign = "right";
    ctx.fillStyle = "#78909c";
    lanes.forEach((text, li) => {
      ctx.fillText(text, GUTTER - 6, row.y + ROW_PAD + li * (LANE_H + LANE_GAP) + LANE_H / 2 + 1);
    });
  }

  /** Logical indices of the frames of `source` (null: all) whose span (shifted in raw mode) meets [t0, t1]. */
  visible(store, source, t0, t1) {
    if (this.scratch.length < store.size) this.scratch = new Int32Array(store.capacity);
    let n = 0;
    // Raw times lie up to clockMax after the corrected ones that the search goes by.
    for (let i = store.firstEndingAfter(t0 - (this.raw ? Math.max(0, store.clockMax) : 0)); i < store.size; i++) {
      const p = store.slot(i);
      const sh = this.shift(store, p);
      if (store.origin[p] + sh > t1 || store.end[p] + sh < t0) continue;
      if (source !== null && store.source[p] !== source) continue;
      this.scratch[n++] = i;
    }
    return this.scratch.subarray(0, n);
  }

  /** What is under (x, y) in CSS px: a bar's details, the row's node (gutter), or null. */
  hit(x, y) {
    const row = this.rows.find((r) => y >= r.y && y < r.y + r.h);
    if (!row) return null;
    if (x < GUTTER) return { gutter: true, node: row.node, header: row.header, source: row.source };
    const li = Math.floor((y - row.y - ROW_PAD + LANE_GAP / 2) / (LANE_H + LANE_GAP));
    if (li < 0 || li >= row.lanes.length) return null;
    const s = row.lanes[li];
    const store = row.store;
    const k = this.plotWidth / (this.t1 - this.t0);
    const t = this.t0 + (x - GUTTER) / k;
    const tol = HIT_PX / k;
    let best = -1;
    let bestDist = Infinity;
    for (let i = store.firstEndingAfter(t - tol - (this.raw ? Math.max(0, store.clockMax) : 0)); i < store.size; i++) {
      const p = store.slot(i);
      if (row.source !== null && store.source[p] !== row.source) continue;
      const sh = this.shift(store, p);
      const a = store.enter[p * store.S + s] + sh;
      const e = store.exit[p * store.S + s] + sh;
      if (!(a <= t + tol && e >= t - tol)) continue;
      const dist = t < a ? a - t : t > e ? t - e : 0;
      if (dist < bestDist || (dist === bestDist && store.stageDelay[p * store.S + s] < this._span(store, best, s))) {
        best = p;
        bestDist = dist;
      }
    }
    if (best < 0) return null;
    const sh = this.shift(store, best);
    const a = store.enter[best * store.S + s] + sh;
    const e = store.exit[best * store.S + s] + sh;
    return {
      node: store.node, stage: store.stages[s], source: store.source[best], frame: store.frame[best],
      enter: a, exit: e, delay: store.stageDelay[best * store.S + s], frameDelay: store.delay[best],
      service: store.stageService[best * store.S + s], wait: store.stageWait[best * store.S + s],
      raw: this.raw, clock: store.clock[best], bound: store.clockBound[best], applied: store.clockApplied,
    };
  }

  _span(store, p, s) {
    return p < 0 ? Infinity : store.stageDelay[p * store.S + s];
  }

  /** Tooltip lines of a hit. */
  static describeHit(h, describe) {
    return [
      `${h.node} · ${h.stage}`,
      `source ${h.source} (${describe(h.node, h.source)}) · frame ${h.frame}`,
      `enter ${formatClockPrecise(h.enter)}  exit ${formatClockPrecise(h.exit)}`,
      `delay ${formatDelay(h.delay)}  (frame end-to-end ${formatDelay(h.frameDelay)})`,
      // Absent where the relay has no split (old traces, Python probes): nothing is guessed.
      ...(h.service === h.service || h.wait === h.wait
        ? [`service ${known(h.service)}  wait ${known(h.wait)}`] : []),
      // Absent where the relay sent no clock (an older relay): nothing is guessed.
      ...(h.bound === h.bound || h.applied ? [StageView.describeClock(h)] : []),
    ];
  }

  /** Which clock a bar's times are on: "raw node clock (...)" or "corrected: ... ± ...". */
  static describeClock(h) {
    const { offset, bound: said } = formatOffsetBound(h.clock, h.bound);  // one unit for both
    const bound = said ? ` ${said}` : "";
    if (h.applied === "none" || h.applied === "ignored") {
      return `${h.raw ? "raw node clock" : "not corrected"}: the relay has no usable clock estimate (${h.applied})`;
    }
    if (h.raw) return `raw node clock (the relay subtracts ${offset}${bound})`;
    return `corrected to the relay's clock (${h.applied ?? "?"}: ${offset} subtracted${bound})`;
  }
}
