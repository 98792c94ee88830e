// Compare view: two stored runs side by side, from GET /api/compare?base=RUN&new=RUN (`dcuscope
// compare`'s document). Every stored run is one entry of BASE and NEW, its value the run's id. Per
// stage, and end to end, a bar for BASE and one for NEW of the chosen figure (mean, p50, p90, p99 of
// delay, service or wait); across NEW's bar a whisker spans its 95 % interval (BASE + the change's
// interval, from the block bootstrap); each value stands right of its bar's track, apart from the
// whisker; beside them the change in ms and in % (with the interval of the %; of the ms where BASE is
// 0) and the verdict. A stage only one run has, and end to end where the runs' stages differ, show their
// values and no change: "not in both" (the document withholds them).

import { esc } from "./panels.js";

const q = encodeURIComponent;
const FEW = "too few frames";
const FEW_TITLE = ' title="fewer than 10 frames beyond this percentile in a run (p99 of fewer than 1,000 frames): its interval means little"';

const APART = "not in both";
/** The figures the view opens on, in this order, the first that some row shown decides: the tail where
 * the runs are long enough for it (1,000 frames for a p99), else the median (20), else the mean. */
const OPENING_FIGURES = ["p99", "p50", "mean"];

const pad = (n) => String(n).padStart(2, "0");

/** A run's start for its entry: "14:03:21" today, else "2026-11-02 14:03" (the browser's time zone). */
function startText(ns, now = new Date()) {
  const d = new Date(ns / 1e6);
  const time = `${pad(d.getHours())}:${pad(d.getMinutes())}`;
  if (d.toDateString() === now.toDateString()) return `${time}:${pad(d.getSeconds())}`;
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${time}`;
}

/** Every stored run of GET /api/sessions, newest first: {run, session, node, stages, label, text}. `label`
 * names it as `dcuscope compare` does (relay.store.runs.run_label: "session 1 · vm", with "· run
 * fcef7528" where the session holds several runs of the node); `text`, its entry, adds its start. */
export function storedRuns(sessions, now = new Date()) {
  const runs = [];
  for (const s of sessions) {
    const count = {};
    for (const r of s.runs) count[r.node] = (count[r.node] ?? 0) + 1;
    for (const r of s.runs) {
      const label = `session ${s.session} · ${r.node}${count[r.node] > 1 ? ` · run ${r.run.slice(0, 8)}` : ""}`;
      runs.push({ run: r.run, session: s.session, node: r.node, stages: r.stages ?? [], first: r.first_seen_ns,
                  label, text: `${label} · ${startText(r.first_seen_ns, now)}${r.ended_ns ? "" : " · recording"}` });
    }
  }
  return runs.sort((a, b) => b.first - a.first);
}

const samePipeline = (a, b) => a.stages.join("\n") === b.stages.join("\n");

/** [BASE, NEW, why] by default among runs (newest first): the two newest runs of one DCU; where no DCU
 * has two, of one pipeline (the same stages); else the two newest runs, of different pipelines. */
export function defaultPair(runs) {
  for (const [same, why] of [[(a, b) => a.node === b.node, "dcu"], [samePipeline, "pipeline"]]) {
    for (let i = 0; i < runs.length; i++) {
      const older = runs.slice(i + 1).find((r) => same(r, runs[i]));
      if (older) return [older, runs[i], why];
    }
  }
  return [runs[1], runs[0], "different"];
}

const signed = (v, places) => `${v >= 0 ? "+" : ""}${v.toFixed(places)}`;
/** Decimals of `v` ms as the CLI's table writes it (compareformat.ms_digits): to the µs, more below
 * 0.1 ms so that it keeps 3 significant digits, to the ns at most. */
const digits = (v) => (v === 0 || Math.abs(v) >= 0.1 ? 3
  : Math.max(3, Math.min(6, 2 - Math.floor(Math.log10(Math.abs(v))))));
const ms = (v) => signed(v, digits(v));
const value = (v) => v.toFixed(digits(v));

/** "+2.049 ms · +96.2 % [+95.1, +97.3]": the difference itself, then in % of BASE with its interval. */
function fmtChange(c) {
  if (!c) return "";
  if (c.pct === null) return `${ms(c.delta)} ms [${ms(c.low)}, ${ms(c.high)}]`;
  return `${ms(c.delta)} ms · ${signed(c.pct, 1)} % [${signed(c.pct_low, 1)}, ${signed(c.pct_high, 1)}]`;
}

const rowName = (r) => (r.stage === "e2e" ? "end to end" : r.stage);
const verdictClass = (v) => `verdict-${v.replace(/ /g, "-")}`;
const shownRows = (doc, kind) => doc.rows.filter((r) => r.kind === kind || (r.stage === "e2e" && kind === "delay"));
const decides = (rows, figure) => rows.some((r) => r.changes[1]?.[figure] && r.changes[1][figure].verdict !== FEW);

/** The figure to open `doc` on for `kind`: the first of OPENING_FIGURES that some row shown decides. */
function openingFigure(doc, kind) {
  const rows = shownRows(doc, kind);
  return OPENING_FIGURES.find((f) => decides(rows, f)) ?? OPENING_FIGURES[0];
}

/** What the rows shown say of `figure`: [text, verdict class]. */
function shownVerdict(rows, figure) {
  const changes = rows.map((r) => [r, r.changes[1]?.[figure]]).filter(([, c]) => c);
  const named = (verdict) => changes.filter(([, c]) => c.verdict === verdict).map(([r]) => rowName(r));
  const [slower, faster, few] = [named("slower"), named("faster"), named(FEW)];
  const parts = [];
  if (slower.length) parts.push(`slower in ${slower.join(", ")}`);
  if (faster.length) parts.push(`faster in ${faster.join(", ")}`);
  const rest = changes.length - slower.length - faster.length - few.length;
  if (!parts.length) {
    if (!changes.length) return [`no row in both runs (${APART})`, "verdict-none"];
    if (!rest) {
      const need = Math.round(10 / (1 - Number(figure.slice(1)) / 100)); // 10 frames beyond it (MIN_TAIL)
      return [`no row decided: ${FEW} (a ${figure} needs ${need.toLocaleString("en")} frames in each run)`, verdictClass(FEW)];
    }
    parts.push(`no significant change in ${rest} row${rest === 1 ? "" : "s"}`);
  }
  if (few.length) parts.push(`${few.length} with ${FEW}`);
  return [parts.join("; "), slower.length ? "verdict-slower" : faster.length ? "verdict-faster" : "verdict-none"];
}

export class CompareView {
  constructor(section, api) {
    this.api = api;
    this.baseSel = section.querySelector("#compare-base");
    this.newSel = section.querySelector("#compare-new");
    this.figureSel = section.querySelector("#compare-figure");
    this.kindSel = section.querySelector("#compare-kind");
    this.body = section.querySelector("#compare-body");
    this.note = section.querySelector("#compare-note");
    this.doc = null;
    this.runs = new Map();
    this.seq = 0;
    this.figurePicked = false; // once a person picks a figure, it stays picked
    for (const sel of [this.baseSel, this.newSel]) sel.addEventListener("change", () => this.load());
    this.figureSel.addEventListener("change", () => { this.figurePicked = true; this.draw(); });
    this.kindSel.addEventListener("change", () => this.draw());
  }

  async show(on) {
    if (!on) return;
    let sessions;
    try {
      sessions = await this.api.get("/api/sessions");
    } catch (err) {
      this.say(`Stored sessions unavailable: ${err.message}`);
      return;
    }
    const runs = storedRuns(sessions);
    this.runs = new Map(runs.map((r) => [r.run, r]));
    if (runs.length < 2) {
      this.say(`Compare needs two stored runs; ${runs.length ? "one is" : "none is"} stored yet (two runs of one DCU compare best).`);
      this.body.innerHTML = "";
      return;
    }
    const options = runs.map((r) => `<option value="${esc(r.run)}">${esc(r.text)}</option>`).join("");
    const [base, next] = [this.baseSel.value, this.newSel.value];
    this.baseSel.innerHTML = options;
    this.newSel.innerHTML = options;
    if (this.runs.has(base) && this.runs.has(next)) {
      [this.baseSel.value, this.newSel.value] = [base, next];
    } else {
      const [older, newer] = defaultPair(runs);
      [this.baseSel.value, this.newSel.value] = [older.run, newer.run];
    }
    await this.load();
  }

  say(text) {
    this.note.textContent = text;
  }

  async load() {
    const [base, next] = [this.baseSel.value, this.newSel.value];
    if (!base || !next) return;
    const seq = ++this.seq;
    this.say("comparing… (resampling each run's frames in blocks)");
    let doc;
    try {
      doc = await this.api.get(`/api/compare?base=${q(base)}&new=${q(next)}`);
    } catch (err) {
      if (seq === this.seq) {
        this.say(`Cannot compare: ${err.message}`);
        this.body.innerHTML = "";
        this.doc = null;
      }
      return;
    }
    if (seq !== this.seq) return;
    this.doc = doc;
    if (!this.figurePicked) this.figureSel.value = openingFigure(doc, this.kindSel.value);
    this.draw();
  }

  draw() {
    const doc = this.doc;
    if (!doc) return;
    const figure = this.figureSel.value;
    const kind = this.kindSel.value;
    const rows = shownRows(doc, kind);
    const top = Math.max(1e-9, ...rows.flatMap((r) => {
      const c = r.changes[1]?.[figure];
      return [r.values[0]?.[figure] ?? 0, r.values[1]?.[figure] ?? 0, c ? (r.values[0]?.[figure] ?? 0) + c.high : 0];
    }));
    const pct = (v) => `${Math.max(0, Math.min(100, (100 * v) / top)).toFixed(2)}%`;
    const [shown, shownClass] = shownVerdict(rows, figure);
    const v = doc.verdicts[1];
    const named = [...v.slower, ...v.faster].slice(0, 5).join(", ");
    const notIn = doc.inputs[1].apart.map((s) => (s === "e2e" ? "end to end" : s));
    const shared = new Set(doc.rows.filter((r) => r.changes[1] && r.stage !== "e2e").map((r) => r.stage));
    const stages = `${shared.size} stage${shared.size === 1 ? "" : "s"}`;
    const apart = notIn.length ? ` · different pipelines: compared on the ${stages} both have; ${APART}, no verdict: ` +
      notIn.join(", ") : "";
    this.say("");
    // The headline is the figure shown, and only that: the whole table's verdict (other figures, other
    // kinds) stands apart below it, uncoloured, so that it never reads as the verdict of these bars.
    const head = `<p class="compare-verdict"><span class="compare-shown ${shownClass}"><b>${esc(figure)} of ${esc(kind)}</b>, ` +
      `NEW against BASE: ${esc(shown)}</span></p>` +
      `<p class="muted compare-inputs">BASE ${esc(doc.inputs[0].label)}: ${doc.inputs[0].frames} frames · ` +
      `NEW ${esc(doc.inputs[1].label)}: ${doc.inputs[1].frames} frames${esc(apart)}</p>` +
      `<p class="muted compare-whole">${v.verdict === APART ? "Nothing in both runs to compare" :
        `Over the whole table (all ${v.figures} figures of every kind, Holm, family-wise 5 %): ` +
        `${esc(v.verdict)}${named ? ` (${esc(named)})` : ""}`}</p>`;
    const body = rows.map((r) => {
      const name = rowName(r);
      const [bv, nv] = [r.values[0], r.values[1]];
      const c = r.changes[1]?.[figure] ?? null;
      const whisker = c && bv ? `<span class="ci" style="left:${pct(bv[figure] + c.low)};width:calc(${pct(bv[figure] + c.high)} - ${pct(bv[figure] + c.low)})"` +
        ` title="95 % interval of NEW: ${value(bv[figure] + c.low)} to ${value(bv[figure] + c.high)} ms"></span>` : "";
      const track = (val, cls, role) => (val ? `<div class="cmp-track ${cls}" title="${role}: ${val.frames} frames">` +
        `<div class="cmp-plot"><span class="cmp-bar ${cls}" style="width:${pct(val[figure])}"></span>${cls === "new" ? whisker : ""}</div>` +
        `<span class="cmp-val">${value(val[figure])} ms</span></div>` : `<div class="cmp-track ${cls} muted">none</div>`);
      // End to end spans the stages only one run has: not in both either, said so.
      const verdict = c ? c.verdict : r.stage === "e2e" && notIn.length ? `${APART}: the stages differ` : APART;
      return `<div class="cmp-row" data-stage="${esc(r.stage)}"><div class="cmp-name" title="${esc(name)}">${esc(name)}</div>` +
        `<div class="cmp-bars">${track(bv, "base", "BASE")}${track(nv, "new", "NEW")}</div>` +
        `<div class="cmp-change ${c ? verdictClass(verdict) : "verdict-apart"}"${verdict === FEW ? FEW_TITLE : ""}>` +
        `${esc(fmtChange(c))}<br><span>${esc(verdict)}</span></div></div>`;
    }).join("");
    this.body.innerHTML = head + `<div class="cmp-key"><span class="swatch cmp-key-base"></span>BASE` +
      ` <span class="swatch cmp-key-new"></span>NEW <span class="swatch cmp-key-ci"></span>NEW's 95 % interval</div>` +
      `<div class="cmp-rows">${body}</div>`;
  }
}
