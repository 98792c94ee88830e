// Moments view: two DCUs processing the same camera, their frames matched by capture time
// (GET /api/moments). Per moment a bar from zero to the difference of their ends (b - a), with
// the clocks' error bar at its tip, coloured by the DCU that finished first; above it the
// aggregate line (mean, p50, p95, who finished first how often, significant or not).

import { esc } from "./panels.js";
import { delayTicks, formatClockPrecise, formatDelay, formatTick, niceCeil } from "./timefmt.js";

export const FIRST_A = "#00897b"; // teal: the first DCU (a) finished first
export const FIRST_B = "#f4511e"; // deep orange: the second DCU (b) finished first
const ERROR_BAR = "#263238";
const GUTTER = 64;
const TOP = 12;
const BOTTOM = 22;
const RIGHT_PAD = 12;
const CANVAS_H = 300;
const POLL_MS = 1000;
const MOMENTS = 300;

const q = encodeURIComponent;

export class MomentView {
  /**
   * @param dcus {opened(): string[], fleet(): string[], sources(node): {id: uri} | undefined}: the opened live
   *   DCUs' names (sorted), every DCU of the fleet, and a DCU's sources as its run header names them
   */
  constructor(section, api, dcus) {
    this.api = api;
    this.dcus = dcus;
    this.selA = section.querySelector("#moments-a");
    this.selB = section.querySelector("#moments-b");
    this.line = section.querySelector("#moments-summary");
    this.canvas = section.querySelector("#moments-canvas");
    this.ctx = this.canvas.getContext("2d", { alpha: false });
    this.data = null;
    this.note = null; // {text, error}: what the line says instead of a summary
    this.timer = null;
    this.last = { moments: 0, bars: { a: 0, b: 0 }, summary: null, message: null, error: null };
    for (const sel of [this.selA, this.selB]) {
      sel.addEventListener("change", () => {
        sel._chosen = true;
        this.poll();
      });
    }
  }

  /** Poll the relay while the view is shown on live data; stop otherwise. */
  show(on) {
    clearInterval(this.timer);
    this.timer = null;
    if (!on) return;
    this.poll();
    this.timer = setInterval(() => this.poll(), POLL_MS);
  }

  /** The menus list the opened DCUs; each keeps its DCU while open, and b is another than a unless the user chose it. */
  syncNodes() {
    const names = this.dcus.opened();
    const html = names.map((n) => `<option value="${esc(n)}">${esc(n)}</option>`).join("");
    if (this.selA._html === html) return;
    const [a, b] = [this.selA.value, this.selB.value];
    for (const sel of [this.selA, this.selB]) {
      sel._html = html;
      sel.innerHTML = html;
    }
    this.selA.value = names.includes(a) ? a : names[0] ?? "";
    const other = names.find((n) => n !== this.selA.value) ?? this.selA.value;
    this.selB.value = names.includes(b) && (b !== this.selA.value || this.selB._chosen) ? b : other;
  }

  async poll() {
    this.syncNodes();
    const a = this.selA.value;
    const b = this.selB.value;
    const missing = missingFor(a, b, this.dcus);
    if (missing) {
      this.say(missing);
      return;
    }
    try {
      this.data = await this.api.get(`/api/moments?a=${q(a)}&b=${q(b)}&limit=${MOMENTS}`);
      this.note = null;
    } catch (err) {
      this.data = null;
      this.note = { text: err.message, error: true };
    }
    this.draw();
  }

  say(note) {
    this.data = null;
    this.note = note;
    this.draw();
  }

  draw() {
    const d = this.data;
    const s = d?.summary;
    const text = this.note?.text ?? (s ? summaryLine(d) : "");
    const error = this.note?.error ? this.note.text : null;
    if (this.line.textContent !== text) this.line.textContent = text;
    this.line.classList.toggle("field-msg", !!error);
    const W = Math.max(240, this.canvas.parentElement.clientWidth - 2);
    const dpr = window.devicePixelRatio || 1;
    if (this.W !== W || this.dpr !== dpr) {
      this.W = W;
      this.dpr = dpr;
      this.canvas.width = Math.round(W * dpr);
      this.canvas.height = Math.round(CANVAS_H * dpr);
      this.canvas.style.width = `${W}px`;
      this.canvas.style.height = `${CANVAS_H}px`;
    }
    const ctx = this.ctx;
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#ffffff";
    ctx.fillRect(0, 0, W, CANVAS_H);
    const moments = d?.moments ?? [];
    this.last = { moments: moments.length, bars: { a: 0, b: 0 }, summary: s ?? null, message: text, error, a: d?.a, b: d?.b };
    if (!moments.length) return;
    this.drawBars(ctx, moments, W, d);
  }

  drawBars(ctx, moments, W, d) {
    const PW = W - GUTTER - RIGHT_PAD;
    const PH = CANVAS_H - TOP - BOTTOM;
    let peak = 0;
    for (const m of moments) peak = Math.max(peak, Math.abs(m.diff_ms) + m.error_ms);
    const ymax = niceCeil(Math.max(peak * 1.05, 0.01));
    const y0 = TOP + PH / 2;
    const ky = PH / 2 / ymax;
    // Axis: ticks both ways from zero, b later above (a finished first), b earlier below.
    const ticks = delayTicks(ymax, PH / 2, 30);
    ctx.font = "11px ui-monospace, SFMono-Regular, Menlo, monospace";
    ctx.textAlign = "right";
    ctx.textBaseline = "middle";
    for (const v of ticks.values) {
      for (const sign of v ? [1, -1] : [1]) {
        const y = Math.round(y0 - sign * v * ky);
        ctx.fillStyle = v ? "#eceff1" : "#90a4ae";
        ctx.fillRect(GUTTER, y, PW, 1);
        ctx.fillStyle = "#455a64";
        ctx.fillText(`${sign < 0 ? "−" : ""}${formatTick(v)}`, GUTTER - 6, y);
      }
    }
    const pitch = PW / moments.length;
    const w = Math.max(1, pitch >= 4 ? pitch - 1 : pitch);
    for (let i = 0; i < moments.length; i++) {
      const m = moments[i];
      const x = GUTTER + i * pitch;
      const tip = y0 - m.diff_ms * ky;
      ctx.fillStyle = m.diff_ms >= 0 ? FIRST_A : FIRST_B;
      this.last.bars[m.diff_ms >= 0 ? "a" : "b"]++;
      ctx.fillRect(x, Math.min(y0, tip), w, Math.max(1, Math.abs(tip - y0)));
      // The error bar: the difference is true within ±error_ms (both clocks' bounds).
      const e = m.error_ms * ky;
      const cx = Math.round(x + w / 2);
      ctx.fillStyle = ERROR_BAR;
      ctx.fillRect(cx, tip - e, 1, Math.max(1, 2 * e));
      if (w >= 3) {
        ctx.fillRect(x, tip - e, w, 1);
        ctx.fillRect(x, tip + e, w, 1);
      }
    }
    ctx.textAlign = "left";
    ctx.textBaseline = "top";
    ctx.fillStyle = "#607d8b";
    ctx.fillText(`${formatClockPrecise(moments[0].capture / 1e6)}`, GUTTER, TOP + PH + 6);
    ctx.textAlign = "right";
    ctx.fillText(`captured ${formatClockPrecise(moments[moments.length - 1].capture / 1e6)}`, GUTTER + PW, TOP + PH + 6);
    ctx.textAlign = "left";
    ctx.fillStyle = FIRST_A;
    ctx.fillText(`▲ ${d.a} first`, GUTTER + 6, TOP + 2);
    ctx.fillStyle = FIRST_B;
    ctx.textBaseline = "bottom";
    ctx.fillText(`▼ ${d.b} first`, GUTTER + 6, TOP + PH - 2);
  }
}

/**
 * What keeps DCUs `a` and `b` (the menus' choices) from having moments, as {text, error}, or null when the
 * relay can be asked: two DCUs open, two different ones, and a camera both read (by the URIs their runs name).
 */
export function missingFor(a, b, dcus) {
  const opened = dcus.opened();
  const fleet = dcus.fleet();
  if (opened.length < 2) {
    if (fleet.length >= 2) {
      const now = opened.length ? `only ${opened[0]} is open` : "none is open";
      return { text: `Moments need two DCUs open: ${now}. Open another in the fleet overview above (click its row).` };
    }
    const now = fleet.length ? `only ${fleet[0]} reports to this relay` : "no DCU reports to this relay yet";
    return { text: `Moments need two DCUs that process the same camera: ${now}.` };
  }
  if (a === b) return { text: `DCU a and DCU b are both ${a}: choose two different DCUs.`, error: true };
  const sa = Object.values(dcus.sources(a) ?? {});
  const sb = Object.values(dcus.sources(b) ?? {});
  if (sa.length && sb.length && !sa.some((u) => sb.includes(u))) {
    const list = (us) => us.map((u) => String(u).replace(/^uri:/, "")).join(", ");
    return { text: `${a} and ${b} read no camera in common (${a}: ${list(sa)}; ${b}: ${list(sb)}). Moments compare `
      + "the frames of one camera on two DCUs: both need it among their sources." };
  }
  return null;
}

/** One line: the verdict, the difference's mean/p50/p95, who finished first how often, what matched. */
export function summaryLine(d) {
  const s = d.summary;
  if (!s.matched) return s.verdict; // the relay says what is missing (relay/api/moments.py none_matched)
  const pct = (x) => `${(100 * x).toFixed(0)}%`;
  return `${s.verdict} · ${d.b} − ${d.a}: mean ${formatDelay(s.diff_ms.mean)}, p50 ${formatDelay(s.diff_ms.p50)}, `
    + `p95 ${formatDelay(s.diff_ms.p95)} · first: ${d.a} ${pct(s.first_share[d.a])}, ${d.b} ${pct(s.first_share[d.b])}`
    + ` · ${s.matched} moments, unmatched ${d.a} ${s.unmatched[d.a]}, ${d.b} ${s.unmatched[d.b]}`;
}
