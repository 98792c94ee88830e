// The dcuscope page: wires the data feeds to the stores, the fleet's overview, the views and the
// panels, and runs the drawing loop. window.dcuscope.debug() reports what was drawn (tests, benchmarks).
//
// Live, only the DCUs opened from the overview are drawn, subscribed to and held: closing one drops
// its frames, so the page's cost follows what it shows, not the fleet's size. ?open=A,B (or * for
// every DCU) says which are opened; without it a fleet of at most AUTO_OPEN_MAX DCUs is opened whole.

import { baseName, legendEntries, StageColours } from "./colours.js";
import { Api, LiveFeed, listSessions, loadSession, SESSION_CAPACITY } from "./feed.js";
import { CompareView } from "./compareview.js";
import { FrameView } from "./frameview.js";
import { HistoryView } from "./historyview.js";
import { HOPS_ROW, JourneyView } from "./journeyview.js";
import { MomentView } from "./momentview.js";
import { Fleet, OPEN_ALL, openedOf, OverviewTable, parseOpen, withOpen } from "./overview.js";
import { installGrip } from "./overviewsize.js";
import { esc, nodesHtml, setHtml, statsHtml } from "./panels.js";
import { showSignIn, signedIn } from "./signin.js";
import { GUTTER, StageView } from "./stageview.js";
import { DELAY_CAPACITY, LIVE_CAPACITY, NodeStore } from "./store.js";
import { formatClock } from "./timefmt.js";

const DEFAULT_WIDTH_MS = 5000;
const MIN_WIDTH_MS = 1;
const MAX_WIDTH_MS = 3 * 3600 * 1000;
const PANEL_REFRESH_MS = 500;
const OVERVIEW_REFRESH_MS = 1000;
const EMPTY_REDRAW_MS = 500; // a live view with no frames to draw: only its axis moves, twice a second is plenty
// A view that scrolls by itself (following the live edge, or a session playing) or takes new frames
// redraws at most every FOLLOW_REDRAW_MS: every other animation frame at 60 Hz (every fourth at 120 Hz,
// fifth at 144 Hz), about 30 draws a second. Redrawn every animation frame, a page following 2 streaming
// DCUs cost headless Chromium 0.49 core; capped, 0.33 (benchmarks/bench_ui.py --follow-cpu). The 5 s
// wide view moves ~10 px a draw instead of ~5: it still reads as scrolling live, and new frames show at
// most 30 ms later. What a person does (a zoom, a drag, a click, the pointer's tooltip) sets view.dirty
// or mouse.fresh and still draws on the next animation frame.
const FOLLOW_REDRAW_MS = 30;
const TIP_MARGIN = 4; // px between the tooltip and the viewport's edges
const STAGE_NAMES = { mux: "frame collection", infer: "neural network", tiler: "collage", convert: "post-processing", osd: "on-screen display" };

const $ = (sel) => document.querySelector(sel);

/** Everything the page knows of one data set: the live relay, or one stored session. */
class Dataset {
  constructor(kind, id = null) {
    this.kind = kind;
    this.id = id;
    this.stores = new Map();
    this.nodes = new Map();
    this.stats = new Map();
    this.span = null;
  }

  sorted() {
    return [...this.stores.keys()].sort().map((k) => this.stores.get(k));
  }
}

const api = new Api();
const colours = new StageColours();
const live = new Dataset("live");
let current = live;
const view = {
  follow: true, width: DEFAULT_WIDTH_MS, end: Date.now(), limit: null, perSource: false, expanded: new Set(), raw: false,
  tab: "stage", windowed: false, frameCount: 75, dirty: true, fresh: false, panelsDirty: true, openGaps: new Set(), openNodes: new Set(),
};
let skewSamples = [];
let skew = 0;
let mouse = null;
let drag = null;
let legendKey = null;

function describe(node, source) {
  const info = current.nodes.get(node);
  return info?.sources?.[String(source)] ?? `source ${source}`;
}

/** The frame delay limit (ms) of a DCU of `ds`: the one set on the page, else the relay's --frame-limit for it, else null. */
function limitOf(ds, node) {
  return view.limit ?? ds.nodes.get(node)?.frame_limit_ms ?? null;
}

/** Bring every store's over-limit count to its DCU's limit (recounted only where it changed). */
function applyLimits() {
  for (const ds of new Set([live, current])) {
    for (const store of ds.stores.values()) {
      const limit = limitOf(ds, store.node);
      if (store.delays.limit !== limit) {
        store.delays.setLimit(limit);
        if (ds === current) view.dirty = true;
      }
    }
  }
}

const model = {
  stores: () => current.sorted(),
  colours,
  expanded: (node) => view.perSource || view.expanded.has(node),
  describe,
  limit: (node) => limitOf(current, node),
  chosenLimit: () => view.limit,
  p99: (node) => current.stats.get(node)?.frame?.p99_ms ?? null,
  raw: () => view.raw,
  empty: () => emptyText(),
};
// The Stage view also draws the hops between DCUs (live data): a row of its own after the DCUs.
const stageView = new StageView($("#stage-canvas"), {
  ...model,
  stores: () => (current === live && journeyView.hops.size ? [...current.sorted(), journeyView.hops] : current.sorted()),
  expanded: (node) => node !== HOPS_ROW && model.expanded(node),
});
const frameView = new FrameView($("#frame-panels"), model);
const historyView = new HistoryView($("#history-view"), api, colours);
const compareView = new CompareView($("#compare-view"), api);
const journeyView = new JourneyView($("#journeys-view"), api);
const momentView = new MomentView($("#moments-view"), api, {
  opened: () => [...live.nodes.keys()].filter(isOpen).sort(),
  fleet: () => fleet.names(),
  sources: (node) => live.nodes.get(node)?.sources,
});

// --- the fleet and the DCUs opened from it ------------------------------------------------------

const fleet = new Fleet();
let choice = parseOpen(location.search); // null: the page chooses (openedOf); OPEN_ALL; or a Set of names
let opened = new Set();
let overviewAt = -Infinity;
let emptySaid = null;

function isOpen(node) {
  return choice === OPEN_ALL || opened.has(node);
}

/** The DCUs shown now, as a new Set (with ?open=*, every row of the fleet). */
function shownNow() {
  return new Set(choice === OPEN_ALL ? fleet.names() : opened);
}

/**
 * Recompute the opened DCUs; release those closed (their frames, statistics, views) and tell the relay.
 * Unless the user named the DCUs, the DCUs the page holds count beside the fleet's rows: a row that
 * expires (its relay restarting, or late) closes nothing, as the page's views never lost a DCU before.
 * Except a DCU whose run ended: its row leaves once the relay lets it go (--limit ended_keep_s), and its
 * views with it (the run is stored: the session list holds it).
 */
function syncOpened() {
  const held = [...live.nodes.keys(), ...live.stores.keys()].filter((n) => fleet.rows.has(n) || !live.nodes.get(n)?.ended);
  const next = openedOf(choice, choice === null || choice === OPEN_ALL ? [...new Set([...fleet.names(), ...held])] : fleet.names());
  const same = next.size === opened.size && [...next].every((n) => opened.has(n));
  if (same && (choice === OPEN_ALL) === (feed.wanted === null)) return;
  for (const node of opened) if (!next.has(node)) release(node);
  opened = next;
  feed.want(choice === OPEN_ALL ? null : [...opened]);
  overviewAt = -Infinity;
  view.dirty = view.panelsDirty = true;
}

/** What the views say while they show no DCU because none is opened (null: none has come yet). */
function emptyText() {
  if (current !== live || opened.size || choice === OPEN_ALL || !fleet.rows.size) return null;
  const n = fleet.rows.size;
  return `No DCU opened: click one of the ${n.toLocaleString("en-US")} DCU${n === 1 ? "" : "s"} in the fleet overview above.`;
}

function release(node) {
  live.stores.delete(node);
  live.stats.delete(node);
  live.nodes.delete(node);
  view.expanded.delete(node);
  view.openGaps.delete(node);
  view.openNodes.delete(node);
}

/** The user's choice: it replaces the page's (and goes in the address, so a link shows the same). */
function choose(next) {
  choice = next;
  history.replaceState(history.state, "", `${location.pathname}${withOpen(location.search, choice)}${location.hash}`);
  syncOpened();
  if (current === live) frameView.sync(); // the closed DCUs' canvases go now, whichever tab shows
}

function toggleOpen(node) {
  const next = shownNow();
  if (next.has(node)) next.delete(node);
  else next.add(node);
  choose(next);
}

function renderOverview(now) {
  overviewAt = now;
  const gone = fleet.expire(Date.now());
  if (gone.length) syncOpened();
  overviewTable.update(fleet, shownNow(), Date.now());
  const empty = emptyText();
  if (empty !== emptySaid) {
    emptySaid = empty;
    // No DCU opened: the overview takes the screen and the views of opened DCUs collapse (style.css).
    document.body.classList.toggle("fleet-only", empty !== null);
    for (const el of document.querySelectorAll(".view-empty")) el.textContent = empty ?? "";
    view.dirty = view.panelsDirty = true;
  }
}

const overviewTable = new OverviewTable($("#overview"), toggleOpen);

// --- relay clock ---------------------------------------------------------------------------

function relayNow() {
  return Date.now() + skew;
}

function noteRelayTime(ms) {
  // relay time at send - local time at receipt = skew - latency <= skew: keep the largest.
  if (ms !== null) {
    skewSamples.push(ms - Date.now());
    if (skewSamples.length > 50) skewSamples = skewSamples.slice(-50);
    skew = Math.max(...skewSamples);
  }
}

// --- live data -------------------------------------------------------------------------------

function ingest(ds, node, block, capacity = LIVE_CAPACITY) {
  colours.learn(block.kinds);
  let store = ds.stores.get(node);
  if (!store) {
    store = new NodeStore(node, block.stages, capacity, ds.kind === "live" ? DELAY_CAPACITY : capacity, limitOf(ds, node));
    ds.stores.set(node, store);
  }
  if (store.ingest(block)) {
    for (const s of store.lanes) colours.get(store.stages[s]);
    if (ds === current) view.fresh = true; // drawn with the next capped redraw (FOLLOW_REDRAW_MS)
  }
}

function setStatus(kind, text) {
  if (current !== live && kind !== "error") return;
  const el = $("#conn");
  el.className = `conn conn-${kind}`;
  el.textContent = text;
  el.title = text; // in full where the header cuts it short
  if (kind === "error" && /unauthori[sz]ed/i.test(text)) {
    showSignIn(`The relay refused this page: ${text}`);
  } else if (kind === "live") {
    showBanner(null);
  }
}

function showBanner(text) {
  const el = $("#banner");
  el.hidden = !text;
  if (text) el.textContent = text;
}

const feed = new LiveFeed(api, {
  nodes(list) {
    fleet.noteNodes(list, Date.now());
    syncOpened();
    for (const n of list) {
      if (!isOpen(n.node)) continue;
      live.nodes.set(n.node, n);
      colours.learn(n.kinds);
    }
    applyLimits(); // a DCU's --frame-limit, once the relay says it
    if (current === live) view.panelsDirty = true;
  },
  frames(node, block) {
    if (isOpen(node)) ingest(live, node, block);
  },
  stats(node, stats) {
    if (!isOpen(node)) return;
    live.stats.set(node, stats);
    if (current === live) view.panelsDirty = true;
    if (current === live && view.tab === "frame") view.fresh = true; // the counts' p99 hint
  },
  overview(msg, keepMs) {
    fleet.merge(msg?.rows, Date.now(), keepMs);
    syncOpened();
  },
  runOf: (node) => fleet.runOf(node),
  names: () => fleet.names(),
  relayTime: noteRelayTime,
  status: setStatus,
  cursor(node, run) {
    const store = live.stores.get(node);
    return store && store.run === run ? store.lastN : 0;
  },
});

// --- stored sessions -------------------------------------------------------------------------

async function refreshSessions() {
  let sessions;
  try {
    sessions = await listSessions(api);
  } catch (err) {
    if (err.status === 401) setStatus("error", err.message);
    return;
  }
  const select = $("#session-select");
  const chosen = select.value;
  const options = [`<option value="live">Live</option>`].concat(sessions.map((s) => {
    const when = s.created_ns ? formatClock(s.created_ns / 1e6).slice(0, 8) : "";
    const nodes = [...new Set(s.runs.map((r) => r.node))].sort();
    // A short entry (the selector is as wide as its longest); every DCU in the entry's tooltip.
    const named = nodes.length > 2 ? `${nodes.slice(0, 2).join(", ")} +${nodes.length - 2}` : nodes.join(", ");
    return `<option value="${s.session}" title="${esc(nodes.join(", "))}">Session ${s.session} · ${when} · ${esc(named)}</option>`;
  }));
  const html = options.join("");
  if (select._html !== html) {
    select._html = html;
    select.innerHTML = html;
    select.value = [...select.options].some((o) => o.value === chosen) ? chosen : "live";
  }
}

async function openSession(id) {
  const ds = new Dataset("session", id);
  current = ds;
  journeyView.follow(false);
  view.follow = false;
  view.dirty = view.panelsDirty = true;
  updatePauseButton();
  updateStatsWindow();
  const bar = $("#progress");
  bar.hidden = false;
  const show = (p) => {
    bar.querySelector(".bar").style.width = `${(100 * p).toFixed(1)}%`;
    bar.querySelector(".text").textContent = `loading session ${id}: ${(100 * p).toFixed(0)}%`;
  };
  show(0);
  $("#conn").className = "conn conn-session";
  $("#conn").textContent = `session ${id}`;
  try {
    const nodes = await loadSession(api, id, {
      onNode(n) {
        if (current !== ds) throw new Error("another data set was chosen");
        ds.nodes.set(n.node, n);
        colours.learn(n.kinds);
        ds.stores.set(n.node, new NodeStore(n.node, n.stages, Math.max(1, Math.min(n.frames, SESSION_CAPACITY)),
          Math.max(1, Math.min(n.frames, SESSION_CAPACITY)), limitOf(ds, n.node)));
        view.panelsDirty = true;
      },
      onBlock(n, block) {
        if (current !== ds) throw new Error("another data set was chosen");
        ingest(ds, n.node, block);
      },
      onStats(node, stats) {
        ds.stats.set(node, stats);
        view.panelsDirty = true;
      },
      progress: show,
    });
    const firsts = nodes.filter((n) => n.first_ns !== null).map((n) => n.first_ns / 1e6);
    const lasts = nodes.filter((n) => n.last_ns !== null).map((n) => n.last_ns / 1e6);
    if (firsts.length) {
      ds.span = [Math.min(...firsts), Math.max(...lasts)];
      if (current === ds) {
        view.width = Math.min(DEFAULT_WIDTH_MS, ds.span[1] - ds.span[0] + 100);
        view.end = ds.span[0] + view.width - 50;
      }
    }
    ds.loaded = true;
  } catch (err) {
    if (current === ds) showBanner(`Cannot load session ${id}: ${err.message}`);
  } finally {
    if (current === ds) bar.hidden = true;
    view.dirty = true;
  }
}

function chooseData(value) {
  mouse = null;
  hideTooltip();
  if (value === "live") {
    current = live;
    journeyView.follow(true);
    view.follow = true;
    view.width = DEFAULT_WIDTH_MS;
    view.dirty = view.panelsDirty = true;
    showBanner(null);
    $("#progress").hidden = true;
    setStatus("live", feed.transport === "polling" ? "polling the HTTP API" : "live");
    updatePauseButton();
    updateStatsWindow();
  } else {
    openSession(value);
  }
}

// --- controls --------------------------------------------------------------------------------

/** The rolling window exists on the live relay only: a stored session says so instead of ignoring the box. */
function updateStatsWindow() {
  const stored = current.kind !== "live";
  $("#stats-window").disabled = stored;
  $("#stats-window-note").hidden = !stored;
}

function updatePauseButton() {
  const b = $("#pause");
  if (current.kind === "live") b.textContent = view.follow ? "Pause" : "Resume";
  else b.textContent = view.follow ? "Pause" : "Play";
}

function togglePause() {
  if (current.kind === "live") {
    if (view.follow) view.end = relayNow();
    view.follow = !view.follow;
  } else if (current.span) {
    if (!view.follow && view.end >= current.span[1]) view.end = current.span[0] + view.width;
    view.follow = !view.follow;
  }
  view.dirty = true;
  updatePauseButton();
}

const CLOCK_TITLES = {
  corrected: "Bars on the relay's clock: each node's correction applied; the band at the start of each row is "
    + "± its uncertainty. Click for each node's raw timestamps.",
  raw: "Bars on each node's own clock, uncorrected (raw = corrected + the offset the relay subtracts). "
    + "Click for corrected timestamps.",
};

/** Corrected (the relay's clock) or raw (each node's own clock) timestamps in the stage view. */
function setClockMode(raw) {
  view.raw = raw;
  const b = $("#clock-mode");
  b.textContent = raw ? "Clock: raw node" : "Clock: corrected";
  b.title = CLOCK_TITLES[raw ? "raw" : "corrected"];
  b.setAttribute("aria-pressed", String(raw));
  view.dirty = true;
}

function resetView() {
  if (current.kind === "live") {
    view.width = DEFAULT_WIDTH_MS;
    view.follow = true;
  } else if (current.span) {
    view.width = Math.max(MIN_WIDTH_MS, current.span[1] - current.span[0]) * 1.02;
    view.end = current.span[1] + view.width * 0.01;
    view.follow = false;
  }
  view.dirty = true;
  updatePauseButton();
}

/** The limit set on the page, in words. */
function limitText() {
  return view.limit === null ? "none (each DCU's own --frame-limit, where the relay has one)" : `${view.limit} ms`;
}

/**
 * Set the frame view's limit for every DCU; an empty box clears it (each DCU's own, else none). Anything
 * but a delay above 0 is refused, saying why, and the box shows the limit in force.
 */
function setLimit(value) {
  const typed = String(value ?? "").trim();
  const v = typed === "" ? null : Number(typed);
  const msg = $("#limit-msg");
  const garbled = typed === "" && $("#limit-input").validity?.badInput; // a number box reads "" for "12,5ms"
  if (garbled || (v !== null && (!(v > 0) || !Number.isFinite(v)))) {
    msg.textContent = `Not set: ${garbled ? "that is not a number" : `“${typed}” is not a delay above 0 ms`}.`
      + ` The limit is still ${limitText()}.`;
    msg.hidden = false;
    $("#limit-input").value = view.limit === null ? "" : String(view.limit);
    return false;
  }
  msg.hidden = true;
  $("#limit-input").value = v === null ? "" : String(v);
  view.limit = v;
  applyLimits();
  view.dirty = true;
  return true;
}

function pause() {
  if (view.follow) {
    if (current.kind === "live") view.end = relayNow();
    view.follow = false;
    updatePauseButton();
  }
}

function stageWheel(ev) {
  ev.preventDefault();
  const rect = ev.currentTarget.getBoundingClientRect();
  const x = ev.clientX - rect.left;
  const factor = Math.exp(Math.max(-300, Math.min(300, ev.deltaY)) * 0.002);
  const width = Math.max(MIN_WIDTH_MS, Math.min(MAX_WIDTH_MS, view.width * factor));
  const following = view.follow && current.kind === "live";
  if (!following && x > GUTTER) {
    // Keep the time under the pointer where it is.
    const frac = Math.min(1, (x - GUTTER) / stageView.plotWidth);
    const tm = view.end - view.width * (1 - frac);
    view.end = tm + width * (1 - frac);
  }
  view.width = width;
  view.dirty = true;
}

function stageMouseDown(ev) {
  const rect = ev.currentTarget.getBoundingClientRect();
  const x = ev.clientX - rect.left;
  const y = ev.clientY - rect.top;
  if (x < GUTTER) {
    const h = stageView.hit(x, y);
    if (h && h.gutter && h.header) {
      if (view.expanded.has(h.node)) view.expanded.delete(h.node);
      else view.expanded.add(h.node);
      view.dirty = true;
    }
    return;
  }
  drag = { x: ev.clientX, end: current.kind === "live" && view.follow ? relayNow() : view.end, moved: false };
}

function windowMouseMove(ev) {
  if (drag) {
    const dx = ev.clientX - drag.x;
    if (Math.abs(dx) > 2 || drag.moved) {
      if (!drag.moved) {
        drag.moved = true;
        pause();
        $("#stage-canvas").classList.add("dragging");
      }
      view.end = drag.end - (dx * view.width) / stageView.plotWidth;
      view.dirty = true;
    }
  }
}

function windowMouseUp() {
  drag = null;
  $("#stage-canvas").classList.remove("dragging");
}

function frameWheel(ev) {
  const canvas = ev.target.closest(".frame-panel");
  const store = canvas && current.stores.get(canvas.dataset.node);
  if (!store || !store.size) return;
  ev.preventDefault();
  pause();
  const hi = store.firstEndingBeyond(view.end);
  const step = Math.max(1, Math.round(view.frameCount / 10)) * Math.sign(ev.deltaY);
  const next = Math.max(1, Math.min(store.size, hi + step));
  view.end = store.maxEnd[store.slot(next - 1)];
  view.dirty = true;
}

function showTooltip(lines, clientX, clientY) {
  const tip = $("#tooltip");
  const text = lines.join("\n");
  if (tip.textContent !== text) tip.textContent = text;
  tip.hidden = false;
  // Beside the pointer, flipped to its other side near an edge, and never out of the viewport
  // (its scroll bars excluded): the CSS caps its size and wraps long lines.
  const w = tip.offsetWidth;
  const h = tip.offsetHeight;
  const vw = document.documentElement.clientWidth;
  const vh = document.documentElement.clientHeight;
  const x = clientX + 14 + w > vw - TIP_MARGIN ? clientX - 14 - w : clientX + 14;
  const y = clientY + 16 + h > vh - TIP_MARGIN ? clientY - 12 - h : clientY + 16;
  tip.style.left = `${Math.max(TIP_MARGIN, Math.min(x, vw - TIP_MARGIN - w))}px`;
  tip.style.top = `${Math.max(TIP_MARGIN, Math.min(y, vh - TIP_MARGIN - h))}px`;
}

function hideTooltip() {
  $("#tooltip").hidden = true;
}

function updateTooltip() {
  if (!mouse || drag?.moved) {
    hideTooltip();
    return;
  }
  const rect = mouse.el.getBoundingClientRect();
  const x = mouse.clientX - rect.left;
  const y = mouse.clientY - rect.top;
  let lines = null;
  if (mouse.kind === "stage") {
    const h = stageView.hit(x, y);
    // A row's name may be cut to fit the gutter: hovering it shows it whole.
    if (h?.gutter) {
      lines = h.header ? [h.node] : [h.node, `source ${h.source}: ${describe(h.node, h.source)}`];
      const band = stageView.last.bands?.[h.node];
      if (band) lines.push(view.raw ? "raw node clock: uncorrected" : `clock ${band.applied ?? "?"}: ${band.label}`);
    }
    else if (h) lines = StageView.describeHit(h, describe);
  } else {
    const h = frameView.hit(mouse.node, x, y);
    if (h) lines = FrameView.describeHit(h, describe, model.limit(h.node));
  }
  if (lines) showTooltip(lines, mouse.clientX, mouse.clientY);
  else hideTooltip();
}

function trackMouse(kind) {
  return (ev) => {
    const el = ev.target.closest("canvas");
    if (!el) return;
    mouse = { kind, el, clientX: ev.clientX, clientY: ev.clientY, node: el.closest(".frame-panel")?.dataset.node };
    mouse.fresh = true;
  };
}

function setTab(tab) {
  view.tab = tab;
  for (const b of document.querySelectorAll(".tab")) b.classList.toggle("active", b.dataset.tab === tab);
  $("#stage-view").hidden = tab !== "stage";
  $("#frame-view").hidden = tab !== "frame";
  $("#moments-view").hidden = tab !== "moments";
  $("#journeys-view").hidden = tab !== "journeys";
  $("#history-view").hidden = tab !== "history";
  $("#compare-view").hidden = tab !== "compare";
  momentView.show(tab === "moments");
  journeyView.show(tab === "journeys");
  historyView.show(tab === "history");
  compareView.show(tab === "compare");
  mouse = null;
  hideTooltip();
  view.dirty = true;
}

// --- drawing loop ----------------------------------------------------------------------------

const perf = {
  frames: new Float64Array(600), // rAF timestamps
  draws: new Float32Array(600), // ms spent drawing per frame
  n: 0,
  record(ts, drawMs) {
    const i = this.n % 600;
    this.frames[i] = ts;
    this.draws[i] = drawMs;
    this.n++;
  },
  summary(lastMs = 5000) {
    const count = Math.min(this.n, 600);
    const newest = this.frames[(this.n - 1 + 600) % 600];
    let k = 0;
    let oldest = newest;
    let sum = 0;
    let max = 0;
    for (let j = 0; j < count; j++) {
      const i = (this.n - 1 - j + 600) % 600;
      if (newest - this.frames[i] > lastMs) break;
      oldest = this.frames[i];
      sum += this.draws[i];
      max = Math.max(max, this.draws[i]);
      k++;
    }
    return { fps: k > 1 ? ((k - 1) * 1000) / (newest - oldest) : 0, drawMsMean: k ? sum / k : 0, drawMsMax: max, frames: k };
  },
};

let lastTs = null;
let panelsAt = -Infinity; // not 0: requestAnimationFrame's clock starts at 0 as the page loads
let drawnAt = -Infinity;
let draws = 0; // the views drawn (debug: an idle page draws twice a second, a following one ~30 times, not every animation frame)
let followRedrawMs = FOLLOW_REDRAW_MS; // window.dcuscope.setFollowRedrawMs: a benchmark's 0 draws every animation frame

function updateLegend() {
  const entries = legendEntries(colours, current.sorted());
  const key = entries.map(([stage, colour]) => `${stage}\u0000${colour}`).join("\u0001");
  if (key === legendKey) return;
  legendKey = key;
  $("#legend").innerHTML = entries.map(([stage, colour]) => {
    const desc = STAGE_NAMES[baseName(stage)];
    return `<span class="legend-item" data-stage="${stage.replace(/[<&"]/g, "")}"><span class="swatch" style="background:${colour}"></span>`
      + `${stage.replace(/[<&]/g, "")}${desc ? ` <span class="desc">${desc}</span>` : ""}</span>`;
  }).join("");
}

function renderPanels() {
  const lineage = (node) => current.nodes.get(node)?.lineage_unknown ?? [];
  const entries = current.sorted().filter((s) => current.stats.has(s.node))
    .map((s) => [s.node, current.stats.get(s.node), s.stages, lineage(s.node)]);
  // Stats of nodes with no frames yet still show (their stages from the nodes list).
  for (const [node, stats] of current.stats) {
    if (!current.stores.has(node)) entries.push([node, stats, current.nodes.get(node)?.stages ?? [], lineage(node)]);
  }
  const none = emptyText() && "No DCU opened."; // the view above says the rest, in its one line
  setHtml($("#stats-body"), none && !entries.length ? `<p class="muted">${esc(none)}</p>`
    : statsHtml(entries, colours, view.windowed && current.kind === "live", view.openGaps));
  const nodes = [...current.nodes.values()].sort((a, b) => (a.node < b.node ? -1 : 1));
  setHtml($("#nodes-body"), none && !nodes.length ? `<p class="muted">${esc(none)}</p>`
    : nodesHtml(nodes, current.kind !== "live", view.openNodes));
}

function frame(ts) {
  requestAnimationFrame(frame);
  const dt = lastTs === null ? 0 : ts - lastTs;
  lastTs = ts;
  if (current.kind === "live") {
    if (view.follow) view.end = relayNow();
  } else if (view.follow && current.span) {
    view.end += dt;
    if (view.end >= current.span[1]) {
      view.end = current.span[1];
      view.follow = false;
      updatePauseButton();
    }
  }
  const t0 = performance.now();
  // Following the live edge redraws at most every FOLLOW_REDRAW_MS while there are frames to scroll
  // (new frames likewise); with none (no DCU opened, or none has sent any), only every EMPTY_REDRAW_MS:
  // a redraw a frame cost an idle page a quarter of a core. A person's input draws at once.
  const empty = current === live && live.stores.size === 0;
  const since = ts - drawnAt;
  if (view.dirty || mouse?.fresh || ((view.fresh || view.follow) && since >= (empty ? EMPTY_REDRAW_MS : followRedrawMs))) {
    drawnAt = ts;
    draws += 1;
    view.dirty = false;
    view.fresh = false;
    if (view.tab === "stage") stageView.draw(view.end - view.width, view.end);
    else if (view.tab === "frame") frameView.draw(view.end, view.frameCount);
    updateTooltip();
    if (mouse) mouse.fresh = false;
    updateLegend();
    const clock = $("#relay-clock");
    const text = formatClock(view.end);
    if (clock.textContent !== text) clock.textContent = text;
  }
  if (ts - overviewAt >= OVERVIEW_REFRESH_MS) renderOverview(ts); // at most once a second, or at once on a click
  if (view.panelsDirty && ts - panelsAt > PANEL_REFRESH_MS) {
    panelsAt = ts;
    view.panelsDirty = false;
    renderPanels();
  }
  perf.record(ts, performance.now() - t0);
}

// --- start -----------------------------------------------------------------------------------

$("#pause").addEventListener("click", togglePause);
$("#zoom-reset").addEventListener("click", resetView);
$("#clock-mode").addEventListener("click", () => setClockMode(!view.raw));
$("#per-source").addEventListener("change", (ev) => {
  view.perSource = ev.target.checked;
  view.expanded.clear();
  view.dirty = true;
});
$("#set-limit").addEventListener("click", () => setLimit($("#limit-input").value));
$("#limit-input").addEventListener("keydown", (ev) => {
  if (ev.key === "Enter") setLimit(ev.target.value);
});
$("#limit-input").addEventListener("input", () => {
  $("#limit-msg").hidden = true;
});
$("#frame-count").addEventListener("change", (ev) => {
  view.frameCount = Number(ev.target.value);
  view.dirty = true;
});
$("#stats-window").addEventListener("change", (ev) => {
  view.windowed = ev.target.checked;
  view.panelsDirty = true;
});
$("#stats-body").addEventListener("toggle", (ev) => {
  // Refreshes rebuild the tables: remember which gaps tables the user opened.
  const node = ev.target.closest(".stats-node")?.dataset.node;
  if (node !== undefined) view.openGaps[ev.target.open ? "add" : "delete"](node);
}, true);
$("#nodes-body").addEventListener("click", (ev) => {
  // A click on a node's row opens its detail row (the clock's reasons in full), kept open across refreshes.
  const node = ev.target.closest("tr.node-row")?.dataset.node;
  if (node === undefined || window.getSelection()?.toString()) return;
  view.openNodes[view.openNodes.has(node) ? "delete" : "add"](node);
  renderPanels();
});
$("#overview-filter").addEventListener("input", () => {
  overviewAt = -Infinity;
});
$("#overview-open").addEventListener("click", () => {
  // Every DCU the filter shows, beside those opened already.
  const next = shownNow();
  for (const r of overviewTable.last.rows) next.add(r.node);
  choose(next);
});
$("#overview-close").addEventListener("click", () => choose(new Set()));
installGrip($(".overview-wrap"), $("#overview-grip"));
document.addEventListener("keydown", (ev) => {
  // "/" focuses the fleet's filter, as in Grafana and GitHub; typed into a field, it is the character.
  if (ev.key !== "/" || ev.ctrlKey || ev.metaKey || ev.altKey || ev.defaultPrevented) return;
  if (ev.target.closest?.("input, textarea, select, [contenteditable]")) return;
  ev.preventDefault();
  const filter = $("#overview-filter");
  filter.focus();
  filter.select();
});
$("#session-select").addEventListener("change", (ev) => chooseData(ev.target.value));
$("#session-select").addEventListener("focus", refreshSessions);
for (const b of document.querySelectorAll(".tab")) b.addEventListener("click", () => setTab(b.dataset.tab));
const stageCanvas = $("#stage-canvas");
stageCanvas.addEventListener("wheel", stageWheel, { passive: false });
stageCanvas.addEventListener("mousedown", stageMouseDown);
stageCanvas.addEventListener("mousemove", trackMouse("stage"));
stageCanvas.addEventListener("mouseleave", () => {
  mouse = null;
  hideTooltip();
});
const panels = $("#frame-panels");
panels.addEventListener("mousemove", trackMouse("frame"));
panels.addEventListener("mouseleave", () => {
  mouse = null;
  hideTooltip();
});
panels.addEventListener("wheel", frameWheel, { passive: false });
window.addEventListener("mousemove", windowMouseMove);
window.addEventListener("mouseup", windowMouseUp);
window.addEventListener("resize", () => {
  view.dirty = true;
});

window.dcuscope = {
  /** What the page holds and last drew: for tests and benchmarks, not an API. */
  debug() {
    const stores = {};
    for (const s of current.sorted()) {
      stores[s.node] = { size: s.size, received: s.received, run: s.run, stages: s.stages, sources: s.sources, lastN: s.lastN };
    }
    const tip = $("#tooltip");
    return {
      mode: current.kind, session: current.id, loaded: current.kind === "live" || !!current.loaded,
      paused: !view.follow, tab: view.tab, window: [view.end - view.width, view.end], limit: view.limit,
      clock: view.raw ? "raw" : "corrected",
      transport: feed.transport, stores, colours: Object.fromEntries(colours.entries()),
      stage: stageView.last, frame: frameView.last, moments: momentView.last, journeys: journeyView.last,
      perf: perf.summary(),
      tooltip: tip.hidden ? null : tip.textContent,
      stats: Object.fromEntries(current.stats), nodes: [...current.nodes.values()],
      overview: { ...overviewTable.last, count: $("#overview-count").textContent, filter: overviewTable.filter },
      opened: choice === OPEN_ALL ? OPEN_ALL : [...opened].sort(), chosen: choice !== null,
      subscription: feed.subscribed, liveStores: [...live.stores.keys()].sort(), draws, followRedrawMs,
    };
  },
  perf: (lastMs) => perf.summary(lastMs),
  setLimit,
  /** Benchmarks: the least ms between the redraws of a following view (0: every animation frame, as before FOLLOW_REDRAW_MS). */
  setFollowRedrawMs(ms) {
    followRedrawMs = ms;
  },
};

setClockMode(false);
syncOpened();
requestAnimationFrame(frame);
if (await signedIn()) {
  feed.start();
  journeyView.follow(current === live);
  refreshSessions();
  setInterval(refreshSessions, 10000);
}
