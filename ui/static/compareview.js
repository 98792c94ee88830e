// Compare view: two stored runs side by side (two sessions, or two runs of one DCU), from
// GET /api/compare (`dcuscope compare`'s document). Per stage, and end to end, a bar for BASE and
// one for NEW of the chosen figure (mean, p50, p90, p99 of delay, service or wait); across NEW's
// bar a whisker spans its 95 % interval (BASE + the change's interval, from the block bootstrap);
// beside it the change in % (ms where BASE is 0) with that interval and the verdict.

import { esc } from "./panels.js";

const FIGURES = ["mean", "p50", "p90", "p99"];
const q = encodeURIComponent;
const FEW_TITLE = ' title="fewer than 10 frames beyond this percentile in a run (p99 of fewer than 1,000 frames): its interval means little"';

function runLabel(s, r) {
  const when = new Date(r.first_seen_ns / 1e6).toISOString().slice(0, 19).replace("T", " ");
  return `Session ${s.session} · ${r.node} · ${when} UTC${r.ended_ns ? "" : " · recording"}`;
}

const signed = (v, digits) => `${v >= 0 ? "+" : ""}${v.toFixed(digits)}`;

function fmtChange(c) {
  if (!c) return "";
  if (c.pct !== null) return `${signed(c.pct, 1)} % [${signed(c.pct_low, 1)}, ${signed(c.pct_high, 1)}]`;
  return `${signed(c.delta, 3)} ms [${signed(c.low, 3)}, ${signed(c.high, 3)}]`;
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
    this.seq = 0;
    for (const sel of [this.baseSel, this.newSel]) sel.addEventListener("change", () => this.load());
    for (const sel of [this.figureSel, this.kindSel]) sel.addEventListener("change", () => this.draw());
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
    const runs = sessions.flatMap((s) => s.runs.map((r) => ({ value: `${s.session}|${r.node}`, label: runLabel(s, r),
                                                           node: r.node })));
    if (runs.length < 2) {
      this.say("Compare needs two stored runs: record two sessions (or two runs of one DCU) first.");
      this.body.innerHTML = "";
      return;
    }
    const options = runs.map((r) => `<option value="${esc(r.value)}">${esc(r.label)}</option>`).join("");
    const [base, next] = [this.baseSel.value, this.newSel.value];
    this.baseSel.innerHTML = options;
    this.newSel.innerHTML = options;
    const values = runs.map((r) => r.value);
    if (values.includes(base) && values.includes(next)) {
      [this.baseSel.value, this.newSel.value] = [base, next];
    } else {
      // Newest first: NEW is the newest run, BASE the one before it of the same DCU (else the next newest).
      const older = runs.slice(1).find((r) => r.node === runs[0].node) ?? runs[1];
      [this.baseSel.value, this.newSel.value] = [older.value, runs[0].value];
    }
    await this.load();
  }

  say(text) {
    this.note.textContent = text;
  }

  async load() {
    const [bs, bn] = this.baseSel.value.split("|");
    const [ns, nn] = this.newSel.value.split("|");
    if (!bs || !ns) return;
    const seq = ++this.seq;
    this.say("comparing… (resampling each run's frames in blocks)");
    let doc;
    try {
      doc = await this.api.get(`/api/compare?base=${q(bs)}&base_node=${q(bn)}&new=${q(ns)}&new_node=${q(nn)}`);
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
    this.draw();
  }

  draw() {
    const doc = this.doc;
    if (!doc) return;
    const figure = this.figureSel.value;
    const kind = this.kindSel.value;
    const rows = doc.rows.filter((r) => r.kind === kind || (r.stage === "e2e" && kind === "delay"));
    const top = Math.max(1e-9, ...rows.flatMap((r) => {
      const c = r.changes[1]?.[figure];
      return [r.values[0]?.[figure] ?? 0, r.values[1]?.[figure] ?? 0, c ? (r.values[0]?.[figure] ?? 0) + c.high : 0];
    }));
    const pct = (v) => `${Math.max(0, Math.min(100, (100 * v) / top)).toFixed(2)}%`;
    const v = doc.verdicts[1];
    const named = [...v.slower, ...v.faster].slice(0, 5).join(", ");
    this.say("");
    const head = `<p class="compare-verdict verdict-${v.verdict.replace(/ /g, "-")}">NEW against BASE: <b>${esc(v.verdict)}</b>` +
      `${named ? ` (${esc(named)})` : ""} <span class="muted">over ${v.figures} figures, family-wise 5 %</span></p>` +
      `<p class="muted compare-inputs">BASE ${esc(doc.inputs[0].label)}: ${doc.inputs[0].frames} frames · ` +
      `NEW ${esc(doc.inputs[1].label)}: ${doc.inputs[1].frames} frames</p>`;
    const body = rows.map((r) => {
      const name = r.stage === "e2e" ? "end to end" : r.stage;
      const [b, n] = [r.values[0], r.values[1]];
      const c = r.changes[1]?.[figure] ?? null;
      const whisker = c && b ? `<span class="ci" style="left:${pct(b[figure] + c.low)};width:calc(${pct(b[figure] + c.high)} - ${pct(b[figure] + c.low)})"` +
        ` title="95 % interval of NEW: ${(b[figure] + c.low).toFixed(3)} to ${(b[figure] + c.high).toFixed(3)} ms"></span>` : "";
      const bar = (val, cls) => (val ? `<div class="cmp-track"><span class="cmp-bar ${cls}" style="width:${pct(val[figure])}"></span>` +
        `${cls === "new" ? whisker : ""}<span class="cmp-val">${val[figure].toFixed(3)} ms</span></div>` : `<div class="cmp-track muted">none</div>`);
      const verdict = c ? c.verdict : "not in both";
      return `<div class="cmp-row" data-stage="${esc(r.stage)}"><div class="cmp-name" title="${esc(name)}">${esc(name)}</div>` +
        `<div class="cmp-bars">${bar(b, "base")}${bar(n, "new")}</div>` +
        `<div class="cmp-change verdict-${verdict.replace(/ /g, "-")}"${verdict === "too few frames" ? FEW_TITLE : ""}>${esc(fmtChange(c))}<br><span>${esc(verdict)}</span></div></div>`;
    }).join("");
    this.body.innerHTML = head + `<div class="cmp-key"><span class="swatch cmp-key-base"></span>BASE` +
      ` <span class="swatch cmp-key-new"></span>NEW <span class="swatch cmp-key-ci"></span>NEW's 95 % interval</div>` +
      `<div class="cmp-rows">${body}</div>`;
  }
}
