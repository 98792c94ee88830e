// Statistics and nodes panels: HTML tables rebuilt from the relay's JSON (only when it changed).

import { pressedWithin } from "./press.js";
import { formatDelay } from "./timefmt.js";

export const esc = (s) => String(s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
const ms = (v) => (v === null || v === undefined ? "–" : formatDelay(v));
const int = (v) => (v === null || v === undefined ? "–" : Number(v).toLocaleString("en-US"));

/**
 * Set innerHTML only when it differs: the panels refresh every second without churning the DOM.
 * Not while a press is inside `el` (its click would be lost): the next refresh after it sets it.
 */
export function setHtml(el, html) {
  if (el._html !== html && !pressedWithin(el)) {
    el._html = html;
    el.innerHTML = html;
  }
}

function summaryCells(s) {
  return `<td>${int(s.count)}</td><td>${ms(s.mean_ms)}</td><td>${ms(s.p50_ms)}</td><td>${ms(s.p95_ms)}</td>`
    + `<td>${ms(s.p99_ms)}</td><td>${ms(s.max_ms)}</td>`;
}

export const RELAY_SILENT = "relay silent"; // a DCU's `state` when the relay holding it stopped refreshing it

/**
 * A live DCU's state and the class of its dot ("up", "ended", "down"): a DCU whose relay went
 * silent is down, whatever that relay last said. `sinceS`: seconds since the relay's answer came.
 */
export function liveState(n, sinceS = 0) {
  if (n.state === RELAY_SILENT) {
    return { text: `${RELAY_SILENT} (${Math.round((n.silent_s ?? 0) + sinceS)} s ago)`, cls: "down" };
  }
  if (n.connected) return { text: "connected", cls: "up" };
  return n.ended ? { text: "ended", cls: "ended" } : { text: "disconnected", cls: "down" };
}

const pct = (v) => (v === null || v === undefined ? "–" : `${(100 * v).toFixed(0)}%`);

/**
 * The relay's verdict: the stage to mark (null: none) and its reason, shown as sent. Older
 * relays send {stage, mean_ms, share}: the stage is marked as before, with no reason.
 */
export function verdict(neck) {
  if (!neck) return { stage: null, reason: null };
  return { stage: neck.saturated === false ? null : neck.stage, reason: neck.reason ?? null };
}

/** Whether the relay split the stages' delays (service, wait, utilization): their columns show then. */
function hasSplit(stages) {
  return Object.values(stages).some((s) => s.service || (s.utilization !== null && s.utilization !== undefined));
}

const LINEAGE_TITLE = "frames enter this stage but its output carries no frame identity "
  + "(it makes new buffers without their metadata): frames cannot be followed past it";

function stageRow(name, s, colours, marked, split, lineageStops) {
  const util = s.utilization === null || s.utilization === undefined ? "–" : pct(s.utilization);
  const extra = split
    ? `<td class="service">${ms(s.service?.mean_ms)}</td><td>${ms(s.service?.p99_ms)}</td>`
      + `<td class="wait">${ms(s.wait?.mean_ms)}</td><td class="utilization">${util}</td>` : "";
  return `<tr data-stage="${esc(name)}"${marked ? ' class="bottleneck"' : ""}>`
    + `<td><span class="swatch" style="background:${colours.get(name)}"></span>${esc(name)}`
    + `${marked ? ' <span class="badge">bottleneck</span>' : ""}`
    + `${lineageStops ? ` <span class="badge lineage" title="${LINEAGE_TITLE}">lineage stops</span>` : ""}`
    + `</td>${summaryCells(s)}${extra}<td>${pct(s.share)}</td></tr>`;
}

const SPLIT_HEAD = `<th title="the stage's own work on the frame or its batch">service mean</th><th>service p99</th>`
  + `<th title="queued, waiting for a batch to form, blocked downstream">wait mean</th>`
  + `<th title="busy fraction of wall time (over 100 %: several threads)">utilization</th>`;

/** Per source: frames delivered, fps against the nominal rate, what was lost before and in the pipeline. */
function sourcesHtml(sources) {
  const rows = Object.entries(sources ?? {}).sort(([a], [b]) => Number(a) - Number(b)).map(([src, v]) => {
    const fps = v.fps === null || v.fps === undefined ? "–" : Number(v.fps).toFixed(1);
    const nominal = v.nominal_fps === null || v.nominal_fps === undefined ? "" : ` of ${Number(v.nominal_fps).toFixed(1)}`;
    const dropped = Object.entries(v.dropped ?? {}).filter(([, n]) => n).map(([why, n]) => `${esc(why)} ${int(n)}`);
    return `<tr data-source="${esc(src)}"><td>source ${esc(src)}</td><td>${int(v.delivered)}</td><td>${fps}${nominal}</td>`
      + `<td>${int(v.lost_upstream)}</td><td>${int(v.decoder_dropped)}</td><td class="dropped">${dropped.join(" · ") || "0"}</td></tr>`;
  }).join("");
  return rows ? `<table class="stats sources"><thead><tr><th>source</th><th>delivered</th><th>fps (of nominal)</th>`
    + `<th>RTP packets lost</th><th>decoder dropped</th><th>dropped (by reason)</th></tr></thead><tbody>${rows}</tbody></table>` : "";
}

const NODE_COUNTS_TITLE = "the node counts these over its whole run, not per frame: no window can hold them";

/** A span in seconds, in the largest units that read well ("52 s", "3 min 07 s", "2 h 05 min"). */
export function spanText(s) {
  const t = Math.max(0, Math.round(s));
  if (t < 60) return `${t} s`;
  const pad = (v) => String(v).padStart(2, "0");
  if (t < 3600) return `${Math.floor(t / 60)} min ${pad(t % 60)} s`;
  return `${Math.floor(t / 3600)} h ${pad(Math.floor((t % 3600) / 60))} min`;
}

/**
 * What a node's block counts, for its title: the window ("last 10 s") or the whole run (its span), and
 * the complete frames every table of the block is over. `win`: the rolling window shown, or null.
 */
export function scopeText(win, full, frames) {
  const n = Number(frames?.complete ?? 0);
  const count = `${n.toLocaleString("en-US")} frame${n === 1 ? "" : "s"}`;
  if (win) return `last ${win.window_s} s · ${count}`;
  const span = full.span_s === null || full.span_s === undefined ? "" : ` (${spanText(full.span_s)})`;
  return `whole run${span} · ${count}`;
}

/**
 * One block per node: stage rows (the relay's bottleneck marked, its reason shown), the
 * end-to-end row, gaps, sources, fps, drops; every figure as the relay computed it.
 * `windowed`: show the relay's rolling window (``stats.window``) instead of the whole run, in every
 * table of the block (the relay counts the window's sources too; the title says which, and its frames);
 * `openGaps`: nodes whose gaps table the user opened (kept open across refreshes).
 * An entry's fourth item: the stages where frame lineage stops (the trace's lineage_unknown).
 */
export function statsHtml(entries, colours, windowed, openGaps = new Set()) {
  if (!entries.length) return `<p class="muted">No statistics yet.</p>`;
  return entries.map(([node, full, order, lineage = []]) => {
    const st = windowed && full.window ? full.window : full;
    const { stage: marked, reason } = verdict(st.bottleneck);
    const stages = st.stages ?? {};
    const split = hasSplit(stages);
    const names = Object.keys(stages).sort((a, b) => order.indexOf(a) - order.indexOf(b));
    for (const name of lineage) if (!(name in stages)) names.push(name);  // it may have no complete frame at all
    const rows = names.map((name) => stageRow(name, stages[name] ?? {}, colours, marked === name, split,
      lineage.includes(name))).join("");
    const gaps = Object.entries(st.gaps ?? {}).map(([name, s]) => `<tr><td>${esc(name)}</td>${summaryCells(s)}<td></td></tr>`).join("");
    const sources = sourcesHtml(st.sources);
    const fps = Object.entries(st.fps ?? {}).map(([src, v]) => `source ${esc(src)}: ${Number(v).toFixed(1)}`).join(" · ") || "–";
    const dropped = full.dropped ?? 0;
    const lost = full.lost ?? 0;
    const frames = st.frames ?? {};
    const scope = scopeText(windowed && full.window ? full.window : null, full, frames);
    // A stored twin's name already holds its run ("vm · run fca2e7ed", relay.store.runs.run_name): not said twice.
    const run = full.run && !String(node).endsWith(` · run ${String(full.run).slice(0, 8)}`)
      ? ` · run ${esc(String(full.run).slice(0, 8))}` : "";
    const session = full.session ? ` · session ${esc(full.session)}` : "";
    return `<div class="stats-node" data-node="${esc(node)}">
      <h3>${esc(node)} <span class="muted">${scope}${run}${session}</span></h3>
      <table class="stats"><thead><tr><th>stage</th><th>frames</th><th>mean</th><th>p50</th><th>p95</th><th>p99</th><th>max</th>${split ? SPLIT_HEAD : ""}<th>share of delay</th></tr></thead>
      <tbody>${rows}<tr class="frame-row"><td>frame (end-to-end)</td>${summaryCells(st.frame ?? {})}${split ? "<td></td>".repeat(4) : ""}<td>100%</td></tr></tbody></table>
      ${reason ? `<p class="bottleneck-reason${marked ? " saturated" : ""}">${esc(reason)}</p>` : ""}
      ${gaps ? `<details${openGaps.has(node) ? " open" : ""}><summary>gaps between stages (queueing, hand-over)</summary>
        <table class="stats"><tbody>${gaps}</tbody></table></details>` : ""}
      ${sources}
      <p class="stats-foot">${sources ? "" : `fps ${fps}<br>`}drops <b class="drops">${int(dropped + lost)}</b> (probe buffer ${int(dropped)}, transport ${int(lost)}${st === full ? "" : `: <span class="whole-run" title="${NODE_COUNTS_TITLE}">whole run</span>`})
      · frames ${int(frames.complete)} complete, ${int(frames.incomplete)} incomplete</p></div>`;
  }).join("");
}

/** µs with its sign (none on what rounds to 0: "−0 µs" reads as a fault). */
const signed = (us) => {
  const text = formatDelay(Math.abs(us) / 1000);
  return text === "0 µs" ? text : `${us >= 0 ? "+" : "−"}${text}`;
};

/** The clock's offset ± its bound as HTML (a muted dash without an estimate): the nodes panel and the overview. */
export function offsetText(clock) {
  if (!clock || clock.offset_us === null || clock.offset_us === undefined) return `<span class="muted">–</span>`;
  return `${signed(clock.offset_us)} ± ${formatDelay(clock.uncertainty_us / 1000)}`;
}

/** Where the clocks and PTP are explained. The relay serves only the page, so the doc is named, not linked. */
export const CLOCK_DOC = "docs/clocks.md";

/**
 * The node's clock in a word or two, from what the relay applies to its timestamps: PTP locked
 * (trusted, nothing subtracted), estimate (the relay's offset subtracted), no estimate yet
 * (nothing subtracted), ignored (a stored correction no relay could compute). The why is elsewhere.
 */
export function clockState(clock, ptp, stored) {
  const applied = clock?.applied;
  if (applied === "ptp") {
    return ptp?.state === "locked" ? { label: "PTP locked", cls: "ok" } : { label: "PTP assumed", cls: "warn" };
  }
  if (applied === "estimate") return { label: "estimate", cls: "est" };
  if (applied === "none" || !applied) return { label: stored ? "uncorrected" : "no estimate yet", cls: "warn" };
  if (applied === "ignored") return { label: "ignored", cls: "bad" };
  return { label: String(applied), cls: "est" };
}

/** PTP as the node reads it, in one word (its reason in the title and the detail row). */
function ptpWord(ptp) {
  if (!ptp || !ptp.state) return `<span class="muted">–</span>`;
  return `<span class="ptp ptp-state ptp-${esc(ptp.state)}"${ptp.reason ? ` title="${esc(ptp.reason)}"` : ""}>${esc(ptp.state)}</span>`;
}

/** PTP in full: state, port state, master offset, grandmaster, timestamping; its reason unless `said` holds it. */
function ptpText(ptp, said) {
  if (!ptp || !ptp.state) return `<span class="muted">no PTP report</span>`;
  const parts = [`<span class="ptp-${esc(ptp.state)}">${esc(ptp.state)}</span>`];
  if (ptp.port_state) parts.push(`port <span class="ptp-port">${esc(ptp.port_state)}</span>`);
  if (ptp.master_offset_ns !== undefined) parts.push(`offset <span class="ptp-offset">${esc(ptp.master_offset_ns)} ns</span>`);
  if (ptp.gm_identity) parts.push(`<span class="ptp-gm">GM ${esc(ptp.gm_identity)}</span>`);
  if (ptp.gm_present === false) parts.push("no grandmaster");
  if (ptp.timestamping) parts.push(`${esc(ptp.timestamping)} timestamps`);
  if (ptp.interface) parts.push(`on ${esc(ptp.interface)}`);
  if (ptp.reason && !said.includes(ptp.reason)) parts.push(`<span class="ptp-reason">${esc(ptp.reason)}</span>`);
  return parts.join(" · ");
}

/** What disciplines the node's CLOCK_REALTIME (what its probes read), and whether that follows PTP. */
function sysclockText(ptp) {
  const sc = ptp?.system_clock;
  if (!sc) return `<span class="muted">not reported</span>`;
  const by = sc.by ? esc(sc.by) : "nothing";
  const follows = sc.follows_ptp ? `<span class="sc-follows">follows PTP</span>` : `<span class="sc-not">not PTP</span>`;
  const synced = sc.synced ? "" : ` · <span class="sc-not">unsynchronised</span>`;
  return `${by} · ${follows}${synced}${sc.detail ? ` · ${esc(sc.detail)}` : ""}`;
}

function driftText(clock) {
  const d = clock?.drift_ppm;
  if (d === null || d === undefined) return "—";
  const unc = clock.drift_uncertainty_ppm;
  return `${d >= 0 ? "+" : "−"}${Math.abs(d).toFixed(2)}${unc !== null && unc !== undefined ? ` ± ${Number(unc).toFixed(2)}` : ""} ppm`;
}

/** The clock in full: the relay's reason (a line of its own), what it subtracts now, what its estimate rests on. */
function clockDetail(clock, stored) {
  const why = [clock.why, clock.ignored && `stored correction ignored: ${clock.ignored}`].filter(Boolean)
    .map((w) => `<span class="clock-why">${esc(w)}</span>`).join("<br>");
  const parts = [];
  if (clock.correction_us !== null && clock.correction_us !== undefined) {
    const bound = clock.correction_uncertainty_ns;
    const value = `${signed(clock.correction_us)}${bound !== null && bound !== undefined ? ` ± ${formatDelay(bound / 1e6)}` : ""}`;
    parts.push(`<span class="clock-correction">${stored ? `last correction ${value}` : `subtracts ${value} now`}</span>`);
  }
  if (clock.samples) {
    const rtt = clock.rtt_us !== null && clock.rtt_us !== undefined ? `, RTT ${formatDelay(clock.rtt_us / 1000)}` : "";
    parts.push(`estimate from ${int(clock.samples)} samples (${int(clock.points)} points${rtt}${clock.via ? ` via ${esc(clock.via)}` : ""})`
      + `${clock.history ? `, ${int(clock.history)} estimates kept` : ""}${clock.restarts ? `, ${int(clock.restarts)} restarts` : ""}`);
  }
  if (clock.rejected) parts.push(`<span class="sc-not">${int(clock.rejected)} samples rejected${clock.rejected_why ? `: ${esc(clock.rejected_why)}` : ""}</span>`);
  if (clock.forged) parts.push(`<span class="sc-not">${int(clock.forged)} UDP answers refused by the node (wrong tag: forged or altered on the way)</span>`);
  if (clock.mode) parts.push(`relay --clock ${esc(clock.mode)}`);
  return [why, parts.join(" · ")].filter(Boolean).join("<br>") || `<span class="muted">–</span>`;
}

/** The row under a node's, opened by a click: the reasons in full, PTP, the system clock, where to read more. */
function nodeDetail(n, clock, ptp, stored, span) {
  const said = `${clock.why ?? ""} ${clock.ignored ?? ""}`;
  return `<tr class="node-detail" data-detail="${esc(n.node)}"><td colspan="${span}"><dl>`
    + `<dt>clock</dt><dd class="clock-detail">${clockDetail(clock, stored)}</dd>`
    + `<dt>PTP</dt><dd class="ptp-cell">${ptpText(ptp, said)}</dd>`
    + `<dt title="what disciplines the node's CLOCK_REALTIME">system clock</dt><dd class="sysclock">${sysclockText(ptp)}</dd>`
    + `<dt>read more</dt><dd class="clock-howto"><code>${CLOCK_DOC}</code> in dcuscope's source: setting up PTP, and the relay's estimate without it</dd>`
    + `</dl></td></tr>`;
}

const NODE_COLUMNS = 10;

/**
 * Nodes table, one short row per node: connection, the clock's state in a word or two with the
 * offset ± uncertainty and drift, PTP's state in a word, counters. The reasons in full, PTP's
 * and the system clock's details and where to read more are in the clock's title and in a detail
 * row that a click on the node's row opens (`open`: the nodes opened, kept across refreshes).
 */
export function nodesHtml(nodes, stored, open = new Set()) {
  if (!nodes.length) return `<p class="muted">No node has connected yet.</p>`;
  const rows = nodes.map((n) => {
    const { text: state, cls } = stored ? { text: n.ended ? "stored" : "stored (incomplete)", cls: "stored" } : liveState(n);
    const clock = n.clock ?? {};
    const ptp = n.ptp ?? clock.ptp;
    const frames = stored ? n.frames : n.frames?.shown;
    const drops = stored ? (n.dropped ?? 0) + (n.lost ?? 0) : n.drops;
    // Another run tried to stream under this name while it was live: refused, and said here.
    const conflict = n.conflicts ? ` <span class="conflict" title="hellos of other runs under this name, refused">`
      + `${int(n.conflicts)} name conflict${n.conflicts > 1 ? "s" : ""}</span>` : "";
    const cs = clockState(clock, ptp, stored);
    const why = [clock.why, clock.ignored && `stored correction ignored: ${clock.ignored}`].filter(Boolean).join("\n");
    const title = `${why ? `${why}\n` : ""}click the row for details · clocks and PTP: ${CLOCK_DOC}`;
    const isOpen = open.has(n.node);
    return `<tr class="node-row${isOpen ? " open" : ""}" data-node="${esc(n.node)}" aria-expanded="${isOpen}">`
      + `<td><span class="node-toggle" aria-hidden="true">${isOpen ? "▾" : "▸"}</span><b>${esc(n.node)}</b></td>`
      + `<td><span class="dot dot-${cls}"></span><span class="conn-state">${state}</span>${conflict}</td>`
      + `<td class="clock-cell" title="${esc(title)}"><span class="clock-state clock-${cs.cls}">${esc(cs.label)}</span></td>`
      + `<td class="clock-offset">${offsetText(clock)}</td><td class="drift">${driftText(clock)}</td>`
      + `<td class="ptp-word">${ptpWord(ptp)}</td>`
      + `<td>${int(n.events)}</td><td>${int(frames)}</td><td>${int(drops)}</td>`
      + `<td class="muted">${esc(String(n.run).slice(0, 8))}</td></tr>`
      + (isOpen ? nodeDetail(n, clock, ptp, stored, NODE_COLUMNS) : "");
  }).join("");
  return `<table class="nodes"><thead><tr><th>DCU</th><th>state</th>`
    + `<th title="what the relay does with the node's timestamps: PTP locked (trusted as they are), estimate (its estimated offset subtracted), no estimate yet">clock</th>`
    + `<th title="node clock − relay clock, as the relay estimates it, ± its bound">offset</th><th>drift</th>`
    + `<th title="the node's ptp4l, as pmc reads it">PTP</th>`
    + `<th>events</th><th>frames</th><th>drops</th><th>run</th></tr></thead><tbody>${rows}</tbody></table>`
    + `<p class="hint">Click a node for its clock's reason, PTP and system clock details.</p>`;
}
