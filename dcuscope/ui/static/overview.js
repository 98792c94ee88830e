// Fleet overview: one compact row per DCU of the fleet (every relay's rows together), worst first,
// filterable; a click on a row opens or closes that DCU's views. Rows come from the relays'
// `overview` pushes and GET /api/overview (merged by node), and, for a relay that sends no
// overview, from its `nodes` lists. The table's rows are keyed DOM rows updated in place: a cell is
// rewritten only when its text changed, and rows move only when the order changed.

import { clockState, esc, liveState, offsetText, RELAY_SILENT } from "./panels.js";
import { pressedWithin } from "./press.js";
import { formatDelay } from "./timefmt.js";

export const ROW_STALE_MS = 3000; // a row nobody refreshed for this long is shown stale
export const ROW_DROP_MS = 5000; // ... and dropped after this long (the relays' ROW_STALE_S)
export const AUTO_OPEN_MAX = 4; // while the user has not chosen, a fleet this small is opened whole
export const OPEN_ALL = "*"; // ?open=* : every DCU of the fleet, those to come included

export const WORST_FIRST = "Worst first: DCUs down or unheard of first (disconnected, their relay silent, or a stale row), "
  + "then most alerts (a stale row counts one), then the busiest bottleneck (its utilization, in whole percent), "
  + "then the longest frame p99, then by name. The order holds still while the pointer is over the table "
  + "or a row has the keyboard's focus.";

/** A row made from a node's entry in a `nodes` list (GET /api/nodes): what a relay without overview tells. */
export function rowFromNode(n) {
  const silent = n.state === RELAY_SILENT;
  const alerts = silent ? [`relay silent: last heard ${Math.round(n.silent_s ?? 0)} s ago`]
    : !n.connected && !n.ended ? ["disconnected"] : [];
  return {
    node: n.node, run: n.run, relay: null, connected: !!n.connected, ended: !!n.ended, fps: null, p99_ms: null,
    frames: n.frames?.shown ?? null, drops: n.drops ?? null, bottleneck: null, clock: n.clock ?? null,
    ptp: n.ptp ?? n.clock?.ptp ?? null, alerts, derived: true,
    ...(silent ? { state: n.state, silent_s: n.silent_s, stale: true } : {}),
  };
}

/** Every relay's rows, merged by node; each row remembers when it was last refreshed (local ms). */
export class Fleet {
  constructor() {
    this.rows = new Map(); // node -> row, with `seen` (local ms) and `keep` (ms it lives unrefreshed)
    this.version = 0; // bumped on every change, so the table knows when to look again
  }

  /**
   * Rows of an `overview` push or of GET /api/overview (`keep`: how long they live unrefreshed;
   * an HTTP answer's rows live until the next poll). A row the relay marks `stale` is shown so.
   * A push's `gone` needs nothing: another relay's rows take those DCUs over, else they age out.
   */
  merge(rows, now, keep = ROW_DROP_MS) {
    for (const r of rows ?? []) {
      if (!r || typeof r.node !== "string") continue;
      this.rows.set(r.node, { ...r, alerts: Array.isArray(r.alerts) ? r.alerts : [], seen: now, keep, derived: false });
    }
    this.version++;
  }

  /** Nodes of a `nodes` list: a row for each that no relay's overview row covers (an older relay's page). */
  noteNodes(list, now) {
    let changed = false;
    for (const n of list ?? []) {
      const had = this.rows.get(n.node);
      if (had && !had.derived && now - had.seen < ROW_DROP_MS) continue;
      this.rows.set(n.node, { ...rowFromNode(n), seen: now, keep: ROW_DROP_MS });
      changed = true;
    }
    if (changed) this.version++;
  }

  /** Drop rows nobody refreshed in time; returns their names. */
  expire(now) {
    const gone = [];
    for (const [node, r] of this.rows) {
      if (now - r.seen > r.keep) {
        this.rows.delete(node);
        gone.push(node);
      }
    }
    if (gone.length) this.version++;
    return gone;
  }

  names() {
    return [...this.rows.keys()];
  }

  runOf(node) {
    return this.rows.get(node)?.run;
  }
}

/** Whether the row is stale: not refreshed for ROW_STALE_MS, or its relay's store says so. */
export function isStale(row, now) {
  return !!row.stale || now - row.seen >= ROW_STALE_MS;
}

/** The row's alerts as shown: the relay's, and the page's own when the row went stale (a silent relay's row says so itself). */
export function alertsOf(row, now) {
  if (!isStale(row, now) || row.state === RELAY_SILENT) return row.alerts;
  const age = Math.max(0, Math.round((now - row.seen) / 1000));
  return [...row.alerts, row.stale ? "stale: its relay stopped refreshing it" : `stale: not refreshed for ${age} s`];
}

const util = (row) => {
  const u = row.bottleneck?.utilization;
  return u === null || u === undefined || !Number.isFinite(u) ? -1 : Math.round(100 * u);
};
const p99 = (row) => (row.p99_ms === null || row.p99_ms === undefined || !Number.isFinite(row.p99_ms) ? -1 : row.p99_ms);

/** Whether the DCU is down or unheard of: disconnected before its run ended (its relay silent included), or its row stale. */
export function isDown(row, now) {
  return (!row.connected && !row.ended) || isStale(row, now);
}

/** The worst-first order (WORST_FIRST says it in words): < 0 when row a comes before row b. */
export function worstFirst(a, b, now) {
  return isDown(b, now) - isDown(a, now) || alertsOf(b, now).length - alertsOf(a, now).length
    || util(b) - util(a) || p99(b) - p99(a) || (a.node < b.node ? -1 : a.node > b.node ? 1 : 0);
}

/** The filter's verdict: every word of `text` is in the row's DCU, relay, bottleneck stage or alerts (any case). */
export function matches(row, text, now) {
  const words = String(text ?? "").toLowerCase().split(/\s+/).filter(Boolean);
  if (!words.length) return true;
  const hay = [row.node, row.relay ?? "", row.bottleneck?.stage ?? "", ...alertsOf(row, now)].join("\n").toLowerCase();
  return words.every((w) => hay.includes(w));
}

// --- the opened DCUs and the address ---------------------------------------------------------

/** ?open= of the address: null (not given: the page chooses), OPEN_ALL, or a Set of names. */
export function parseOpen(search) {
  const m = /[?&]open=([^&]*)/.exec(search ?? "");
  if (!m) return null;
  if (m[1] === OPEN_ALL) return OPEN_ALL;
  const names = m[1].split(",").filter(Boolean).map((s) => {
    try {
      return decodeURIComponent(s.replace(/\+/g, " "));
    } catch (_) {
      return s;
    }
  });
  return new Set(names);
}

/** `search` with ?open= saying `choice` (its other parameters kept); null removes it. */
export function withOpen(search, choice) {
  const rest = String(search ?? "").replace(/^\?/, "").split("&").filter((p) => p && !/^open(=|$)/.test(p));
  if (choice !== null) {
    const value = choice === OPEN_ALL ? OPEN_ALL
      : [...choice].sort().map((n) => encodeURIComponent(n).replace(/\*/g, "%2A")).join(",");
    rest.push(`open=${value}`);
  }
  return rest.length ? `?${rest.join("&")}` : "";
}

/**
 * The DCUs whose views are drawn: the user's choice (a set, or every DCU), else, while the fleet
 * has at most AUTO_OPEN_MAX DCUs, all of them, else none.
 */
export function openedOf(choice, names) {
  if (choice === OPEN_ALL) return new Set(names);
  if (choice !== null) return new Set(choice);
  return names.length <= AUTO_OPEN_MAX ? new Set(names) : new Set();
}

// --- the table -----------------------------------------------------------------------------------

const int = (v) => (v === null || v === undefined ? "–" : Number(v).toLocaleString("en-US"));
const dash = `<span class="muted">–</span>`;

/** The fps cell: "ended" for a run that ended (it has no rate), else the relay's figure over its window. */
function fpsCell(row) {
  if (row.ended) return `<span class="muted" title="the DCU's run ended">ended</span>`;
  return row.fps === null || row.fps === undefined ? dash : Number(row.fps).toFixed(1);
}

export const WHOLE_RUN_TITLE = "the DCU's run ended: its whole run's figures, as they stood at its end";

/** The p99 cell: over the window, or, once the run ended, over its whole run (said so: no window is left to drift). */
function p99Cell(row) {
  if (row.p99_ms === null || row.p99_ms === undefined) return dash;
  const text = esc(formatDelay(row.p99_ms));
  return row.figures === "whole run" ? `${text} <span class="muted figures" title="${WHOLE_RUN_TITLE}">whole run</span>` : text;
}

/** The cells of a row as HTML, in column order (the table rewrites a cell only when its HTML changed). */
export function rowCells(row, isOpen, now) {
  const { text: stateText, cls: state } = liveState(row, Math.max(0, (now - row.seen) / 1000));
  const silent = row.state === RELAY_SILENT;
  const stale = isStale(row, now);
  const neck = row.bottleneck;
  const u = neck?.utilization;
  const cs = clockState(row.clock, row.ptp, false);
  const alerts = alertsOf(row, now);
  const age = Math.max(0, Math.round((now - row.seen) / 1000));
  return [
    `<span class="node-toggle" aria-hidden="true">${isOpen ? "▾" : "▸"}</span>`
      + `<span class="dot dot-${state}" title="${esc(stateText)}"></span>`
      + `<b class="ov-name">${esc(row.node)}</b>`,
    `${row.relay === null || row.relay === undefined ? dash : esc(row.relay)}`
      + `${stale ? ` <span class="badge stale" title="${row.stale ? "its relay stopped refreshing it" : `not refreshed for ${age} s`}">`
        + `${silent ? esc(stateText) : "stale"}</span>` : ""}`,
    fpsCell(row),
    p99Cell(row),
    neck?.stage ? `${esc(neck.stage)}${u === null || u === undefined ? "" : ` <b>${Math.round(100 * u)} %</b>`}` : dash,
    `<span class="clock-state clock-${cs.cls}">${esc(cs.label)}</span> <span class="ov-offset">${offsetText(row.clock)}</span>`,
    int(row.drops),
    alerts.length ? `<span class="badge alert-count">${alerts.length}</span> ${esc(alerts.join(" · "))}` : dash,
  ];
}

export const COLUMNS = [
  ["DCU", "click a row to open or close the DCU's stage, frame and moments views"],
  ["relay", "the relay holding the DCU"],
  ["fps", "frames per second over the relay's rolling window (its last 10 s), all sources: 0 when no frame came in it, \"ended\" once the DCU's run ended"],
  ["frame p99", "end-to-end frame delay, 99th percentile over the window; once the DCU's run ended, over its whole run (said so)"],
  ["bottleneck", "the relay's bottleneck stage and its utilization (busy share of wall time), over the same span as the p99"],
  ["clock", "what the relay does with the DCU's timestamps; node clock − relay clock ± its bound"],
  ["drops", "frames dropped"],
  ["alerts", "the relay's alerts, and the page's when a row is stale"],
];

export class OverviewTable {
  /**
   * @param root the overview <section>: #overview-filter, #overview-count, #overview-order, #overview-hint,
   *   a <table> with a <thead> row (filled here) and a <tbody>
   * @param onToggle (node) => void: a click on a row
   */
  constructor(root, onToggle) {
    this.root = root;
    this.body = root.querySelector("tbody");
    this.filterBox = root.querySelector("#overview-filter");
    this.countEl = root.querySelector("#overview-count");
    this.hintEl = root.querySelector("#overview-hint");
    this.trs = new Map(); // node -> <tr>, with _cells and _html
    this.order = []; // nodes in table order (all rows, filtered ones hidden)
    this.last = { rows: [], shown: 0, total: 0 };
    this.body.addEventListener("click", (ev) => {
      const tr = ev.target.closest("tr[data-node]");
      if (tr && !window.getSelection()?.toString()) onToggle(tr.dataset.node);
    });
    this.body.addEventListener("keydown", (ev) => this.rowKey(ev, onToggle));
    this.filterBox.addEventListener("keydown", (ev) => {
      if (ev.key !== "ArrowDown" || ev.altKey || ev.ctrlKey || ev.metaKey) return;
      ev.preventDefault();
      this.focusRow(this.visibleRows()[0]);
    });
    // The order holds still while the pointer is over the rows, or one of them has the keys' focus.
    this.pointerIn = false;
    this.focusIn = false;
    this.body.addEventListener("mouseenter", () => { this.pointerIn = true; });
    this.body.addEventListener("mouseleave", () => { this.pointerIn = false; });
    this.body.addEventListener("focusin", () => { this.focusIn = true; });
    this.body.addEventListener("focusout", (ev) => { this.focusIn = this.body.contains(ev.relatedTarget); });
    const head = root.querySelector("thead tr");
    head.innerHTML = COLUMNS.map(([name, title]) => `<th class="ov-${name.replace(/\s+/g, "-")}" title="${esc(title)}">${esc(name)}</th>`).join("");
    root.querySelector("#overview-order").title = WORST_FIRST;
  }

  get filter() {
    return this.filterBox.value;
  }

  get hold() {
    return this.pointerIn || this.focusIn;
  }

  /** The rows the filter shows, in table order. */
  visibleRows() {
    return [...this.body.children].filter((tr) => !tr.hidden);
  }

  focusRow(tr) {
    if (!tr) return;
    tr.focus({ preventScroll: true });
    tr.scrollIntoView({ block: "nearest" }); // within the overview's box, clear of its sticky head
  }

  /** Keys on a row: up and down (Home, End) move, Enter or space opens or closes, Escape goes to the filter. */
  rowKey(ev, onToggle) {
    const tr = ev.target.closest("tr[data-node]");
    if (!tr || ev.altKey || ev.ctrlKey || ev.metaKey) return;
    const rows = this.visibleRows();
    const i = rows.indexOf(tr);
    const to = { ArrowDown: i + 1, ArrowUp: i - 1, Home: 0, End: rows.length - 1 }[ev.key];
    if (ev.key === "Enter" || ev.key === " ") {
      onToggle(tr.dataset.node);
    } else if (ev.key === "Escape") {
      this.filterBox.focus();
    } else if (to !== undefined) {
      if (ev.key === "ArrowUp" && i === 0) this.filterBox.focus(); // above the first row: the filter
      else this.focusRow(rows[Math.max(0, Math.min(rows.length - 1, to))]);
    } else {
      return;
    }
    ev.preventDefault();
  }

  row(node) {
    let tr = this.trs.get(node);
    if (!tr) {
      tr = document.createElement("tr");
      tr.dataset.node = node;
      tr.tabIndex = 0; // the keys: see rowKey
      tr._cells = COLUMNS.map(([name]) => {
        const td = document.createElement("td");
        td.className = `ov-${name.replace(/\s+/g, "-")}`;
        tr.appendChild(td);
        return td;
      });
      tr._html = [];
      this.trs.set(node, tr);
    }
    return tr;
  }

  /**
   * Show `fleet`'s rows: `opened` marked, the filter applied, worst first (unless held). Not while a
   * press is on the rows (a cell rewritten under it would lose its click): the next refresh shows them.
   */
  update(fleet, opened, now) {
    if (pressedWithin(this.body)) return;
    const rows = [...fleet.rows.values()];
    for (const [node, tr] of this.trs) {
      if (!fleet.rows.has(node)) {
        tr.remove();
        this.trs.delete(node);
      }
    }
    let order;
    if (this.hold) {
      const had = new Set(this.order.filter((n) => fleet.rows.has(n)));
      order = [...had, ...rows.filter((r) => !had.has(r.node)).sort((a, b) => worstFirst(a, b, now)).map((r) => r.node)];
    } else {
      order = rows.sort((a, b) => worstFirst(a, b, now)).map((r) => r.node);
    }
    const focused = this.body.contains(document.activeElement) ? document.activeElement : null;
    const filter = this.filter;
    let shown = 0;
    const listed = [];
    order.forEach((node, i) => {
      const r = fleet.rows.get(node);
      const tr = this.row(node);
      const isOpen = opened.has(node);
      const html = rowCells(r, isOpen, now);
      for (let k = 0; k < html.length; k++) {
        if (tr._html[k] !== html[k]) {
          tr._html[k] = html[k];
          tr._cells[k].innerHTML = html[k];
        }
      }
      const stale = isStale(r, now);
      const alerting = alertsOf(r, now).length > 0;
      const cls = `ov-row${isOpen ? " open" : ""}${stale ? " stale" : ""}${alerting ? " alerting" : ""}`;
      if (tr.className !== cls) tr.className = cls;
      tr.setAttribute("aria-expanded", String(isOpen));
      const hide = !matches(r, filter, now);
      if (tr.hidden !== hide) tr.hidden = hide;
      if (!hide) {
        shown++;
        listed.push({ node, relay: r.relay ?? null, open: isOpen, stale, down: isDown(r, now), alerts: alertsOf(r, now),
          util: util(r), p99: p99(r) });
      }
      if (this.body.children[i] !== tr) this.body.insertBefore(tr, this.body.children[i] ?? null);
    });
    this.order = order;
    // A row moved in the DOM loses the focus: the keys' place is kept.
    if (focused && document.activeElement !== focused && focused.isConnected && !focused.hidden) {
      focused.focus({ preventScroll: true });
    }
    const total = rows.length;
    const count = `${shown.toLocaleString("en-US")} of ${total.toLocaleString("en-US")} DCU${total === 1 ? "" : "s"}`
      + ` · ${opened.size.toLocaleString("en-US")} opened`;
    if (this.countEl.textContent !== count) this.countEl.textContent = count;
    const hint = !total ? "No DCU has reported yet." : ""; // else the keys' line beside it says what a row does
    if (this.hintEl.textContent !== hint) this.hintEl.textContent = hint;
    this.last = { rows: listed, shown, total, opened: opened.size };
  }
}
