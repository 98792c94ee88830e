// Where the page's data comes from: the relay's Socket.IO namespace /ui (live pushes), its HTTP
// API (backfill, statistics, the fleet's overview, stored sessions), or polling the API when the
// Socket.IO client is not installed. A relay that asks for a credential gets the session cookie the
// page signed in with (signin.js), which the browser sends with every request, engine.io's included.
//
// The page subscribes to the DCUs it shows (`want`): the relay pushes frames, statistics and node
// views of those only, and the fleet's overview rows (a row per DCU) to every page; frames and
// statistics of other DCUs are neither asked for nor backfilled.

export const BACKFILL_FRAMES = 2000;
export const SESSION_PAGE = 10000;
export const SESSION_CAPACITY = 262144; // frames per node a stored session is browsed with, at most
const POLL_FRAMES_MS = 250;
const POLL_SLOW_MS = 1000;
export const OVERVIEW_DOWN_MS = 5000; // GET /api/overview this often while the socket is down
export const PUSH_MAX_FRAMES = 25; // frames per DCU and push asked of the relay
export const UNREACHABLE = "relay unreachable, retrying";
const MISSING = -1n; // dcuscope/model/frametable.py: no time at this point (packed frames)

/**
 * What the user is told of a failed request or connection: [status kind, text]. Transport
 * failures (a fetch that never got an answer, Socket.IO's "xhr poll error") mean the relay is
 * down or restarting, which the page recovers from by itself; an answer (a refused token, an
 * HTTP error) is shown as it is.
 */
export function failure(err) {
  const text = err?.message || String(err);
  if (err?.status !== undefined || /unauthori[sz]ed/i.test(text)) return ["error", text];
  return ["down", UNREACHABLE];
}

export class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

export class Api {
  async get(path) {
    const r = await fetch(path, { cache: "no-store" });
    if (!r.ok) {
      let message = `${r.status} ${r.statusText}`;
      try {
        message = (await r.json()).error ?? message;
      } catch (_) { /* not JSON */ }
      throw new ApiError(r.status, message);
    }
    return r.json();
  }
}

const q = encodeURIComponent;

/** An ArrayBuffer of a binary attachment (a browser's socket.io-client gives one; a view is copied). */
function arrayBuffer(data) {
  return data instanceof ArrayBuffer ? data : data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength);
}

/**
 * A pushed block with its frames unpacked: the relay packs them in two binary columns blocks
 * (relay/live/framepack.py: int64 and float64, one row per field and stage); unpacked, each frame
 * is the object GET /api/frames gives (MISSING times and NaN figures as null).
 */
export function unpackFrames(block) {
  const p = block.packed;
  if (!p) return block;
  const k = p.count;
  const ints = k ? new BigInt64Array(arrayBuffer(p.ints)) : new BigInt64Array(0);
  const floats = k ? new Float64Array(arrayBuffer(p.floats)) : new Float64Array(0);
  const frames = Array.from({ length: k }, () => ({}));
  const read = (layout, values, convert) => {
    let row = 0;
    for (const [name, rows] of layout) {
      const list = rows > 1 || name === "enter" || name === "exit" || name.startsWith("stage_");
      for (let i = 0; i < k; i++) {
        if (list) {
          const out = new Array(rows);
          for (let s = 0; s < rows; s++) out[s] = convert(name, values[(row + s) * k + i]);
          frames[i][name] = out;
        } else {
          frames[i][name] = convert(name, values[row * k + i]);
        }
      }
      row += rows;
    }
  };
  read(p.int_fields, ints, (name, v) => {
    if (name === "complete") return v !== 0n;
    if ((name === "enter" || name === "exit" || name === "capture") && v === MISSING) return null;
    return Number(v);
  });
  read(p.float_fields, floats, (_, v) => (Number.isNaN(v) ? null : v));
  const { packed: _, ...rest } = block;
  return { ...rest, frames };
}


/**
 * Live data. `sink` receives: nodes(list), frames(node, block), stats(node, stats),
 * overview(answer, keepMs) (an `overview` push or GET /api/overview: rows that live keepMs
 * unrefreshed), relayTime(ms), status(kind, text); `cursor(node, run)` says which frame it holds
 * last, `runOf(node)` the run the fleet's rows name (or undefined), `names()` every DCU known.
 */
export class LiveFeed {
  constructor(api, sink) {
    this.api = api;
    this.sink = sink;
    this.known = new Map(); // node -> run last seen in `nodes`
    this.pending = new Map(); // node -> frames blocks pushed while its backfill runs
    this.transport = null;
    this.socket = null;
    this.resync = new Set(); // nodes to backfill once the relay lists them again after a reconnect
    this.wanted = new Set(); // the DCUs the page shows: null for every one
    this.subscribed = null; // the last subscription sent, and the relay's answer (debug)
    this.overviewTimer = null;
  }

  wants(node) {
    return this.wanted === null || this.wanted.has(node);
  }

  /**
   * Show these DCUs (null: every one): tell the relay, forget the others (their backfills end
   * unread: the sink ignores what it does not show), and fetch those whose run is known already.
   */
  want(nodes) {
    this.wanted = nodes === null ? null : new Set(nodes);
    for (const node of [...this.known.keys()]) {
      if (!this.wants(node)) {
        this.known.delete(node);
        this.resync.delete(node);
      }
    }
    this.sendSubscription();
    if (this.transport !== "socket.io") return; // polling: the next round fetches them
    const names = this.wanted === null ? this.sink.names() : this.wanted;
    for (const node of names) {
      const run = this.sink.runOf(node);
      if (this.known.has(node) || run === undefined || run === null) continue; // the next `nodes` list starts it
      this.known.set(node, run);
      this.backfill(node);
      this.fetchStats(node);
    }
  }

  /** What the page shows, as the relay's `subscribe` takes it. */
  subscription() {
    return { nodes: this.wanted === null ? null : [...this.wanted].sort(), max_frames: PUSH_MAX_FRAMES, overview: true };
  }

  sendSubscription() {
    if (!this.socket?.connected) return; // sent on (re)connect
    const msg = this.subscription();
    const sent = { ...msg, ack: null };
    this.subscribed = sent;
    this.socket.emit("subscribe", msg, (ack) => {
      sent.ack = ack ?? null;
    });
  }

  fetchStats(node) {
    this.api.get(`/api/stats?node=${q(node)}`).then((s) => this.sink.stats(node, s), () => {});
  }

  /** The whole fleet's rows from any relay (an older relay without /api/overview: nothing, the nodes lists tell). */
  async fetchOverview(keepMs) {
    try {
      this.sink.overview(await this.api.get("/api/overview"), keepMs);
    } catch (_) { /* the other requests report a relay that is down */ }
  }

  start() {
    if (typeof window.io === "function") this.startSocket();
    else this.startPolling("the Socket.IO client (vendor/socket.io.min.js) is not installed");
    if (this.transport === "socket.io") this.fetchOverview(OVERVIEW_DOWN_MS); // before the socket connects
  }

  startSocket() {
    this.transport = "socket.io";
    // The subscription goes with every (re)connection, so that the relay pushes nothing else meanwhile
    // (without it, every DCU until the `subscribe` below arrives).
    const auth = (cb) => cb({ subscribe: this.subscription() });
    const socket = window.io("/ui", { auth, reconnectionDelayMax: 5000 });
    this.socket = socket;
    socket.on("connect", () => {
      this.sink.status("live", "live");
      this.sendSubscription();
      clearInterval(this.overviewTimer);
      this.overviewTimer = null;
      this.fetchOverview(OVERVIEW_DOWN_MS);
      // After a reconnect the pushes went on without us: fetch what was missed, once the relay
      // (perhaps restarted, its nodes not back yet) lists the node again.
      this.resync = new Set(this.known.keys());
    });
    socket.on("connect_error", (err) => this.sink.status(...failure(err)));
    // A relay that stops closes the transport: Socket.IO calls again by itself, with backoff.
    // Meanwhile any relay of the fleet answers for the overview.
    socket.on("disconnect", () => {
      this.sink.status("down", UNREACHABLE);
      clearInterval(this.overviewTimer);
      this.overviewTimer = setInterval(() => this.fetchOverview(OVERVIEW_DOWN_MS + POLL_SLOW_MS), OVERVIEW_DOWN_MS);
    });
    socket.on("nodes", (list) => this.onNodes(list));
    socket.on("overview", (msg) => this.sink.overview(msg));
    socket.on("frames", (msg) => {
      this.sink.relayTime(msg.t_ns / 1e6);
      for (const [node, packed] of Object.entries(msg.nodes)) {
        if (!this.wants(node)) continue; // pushed before the relay had our last subscription
        const block = unpackFrames(packed);
        const queue = this.pending.get(node);
        if (queue) {
          queue.push(block);
        } else if (block.frames.length && block.frames[0].n > this.sink.cursor(node, block.run) + 1) {
          // The relay pushes at most its newest frames per tick: fetch the ones it skipped.
          this.backfill(node, [block]);
        } else {
          this.sink.frames(node, block);
        }
      }
    });
    socket.on("stats", (msg) => {
      for (const [node, stats] of Object.entries(msg.nodes)) this.sink.stats(node, stats);
    });
  }

  onNodes(list) {
    this.sink.nodes(list);
    for (const n of list) {
      if (!this.wants(n.node)) continue;
      const stale = this.resync.delete(n.node);
      if (this.known.get(n.node) !== n.run) {
        this.known.set(n.node, n.run);
        this.backfill(n.node);
        this.fetchStats(n.node);
      } else if (stale) {
        this.backfill(n.node);
      }
    }
  }

  /** Fetch the frames after the page's cursor, holding back pushes (`held`, then new ones) until they are in. */
  async backfill(node, held = []) {
    if (this.pending.has(node)) {
      this.pending.get(node).push(...held);
      return;
    }
    this.pending.set(node, held);
    try {
      const run = held.length ? held[0].run : this.known.get(node);
      for (;;) {
        const since = this.sink.cursor(node, run);
        const block = await this.api.get(`/api/frames?node=${q(node)}&since=${since}&limit=${BACKFILL_FRAMES}`);
        this.sink.frames(node, block);
        if (block.frames.length < BACKFILL_FRAMES || block.run !== run) break;
      }
    } catch (err) {
      // 404: the relay no longer has the node (it restarted); it backfills when listed again.
      if (err.status === 404) this.resync.add(node);
      else this.sink.status(...failure(err));
    } finally {
      const queue = this.pending.get(node) ?? [];
      this.pending.delete(node);
      for (const block of queue) this.sink.frames(node, block);
    }
  }

  startPolling(why) {
    this.transport = "polling";
    this.sink.status("live", `polling the HTTP API (${why})`);
    const slow = async () => {
      try {
        this.fetchOverview(OVERVIEW_DOWN_MS);
        const list = await this.api.get("/api/nodes");
        this.sink.nodes(list);
        for (const n of list) {
          if (!this.wants(n.node)) continue;
          this.known.set(n.node, n.run);
          this.sink.stats(n.node, await this.api.get(`/api/stats?node=${q(n.node)}`));
        }
        this.sink.status("live", `polling the HTTP API (${why})`);
      } catch (err) {
        this.sink.status(...failure(err));
      }
    };
    const fast = async () => {
      for (const [node, run] of this.known) {
        try {
          const since = this.sink.cursor(node, run);
          const block = await this.api.get(`/api/frames?node=${q(node)}&since=${since}&limit=${BACKFILL_FRAMES}`);
          this.sink.frames(node, block);
        } catch (_) { /* the slow loop reports errors */ }
      }
      this.sink.relayTime(null);
    };
    slow();
    setInterval(slow, POLL_SLOW_MS);
    const loop = async () => {
      await fast();
      setTimeout(loop, POLL_FRAMES_MS);
    };
    loop();
  }
}

/** Stored sessions, newest first, as GET /api/sessions gives them. */
export function listSessions(api) {
  return api.get("/api/sessions");
}

/**
 * A stored session: its nodes, every complete frame (up to SESSION_CAPACITY per node, paged) and
 * statistics. `onBlock(summary, block)` gets the frames as they arrive; `progress(0..1)`.
 */
export async function loadSession(api, id, { onNode, onBlock, onStats, progress }) {
  const nodes = await api.get(`/api/sessions/${q(id)}/nodes`);
  const total = nodes.reduce((a, n) => a + Math.min(n.frames, SESSION_CAPACITY), 0);
  let done = 0;
  for (const n of nodes) {
    onNode(n);
    api.get(`/api/sessions/${q(id)}/stats?node=${q(n.node)}`).then((s) => onStats(n.node, s), () => {});
    let since = 0;
    const want = Math.min(n.frames, SESSION_CAPACITY);
    while (since < want) {
      const block = await api.get(`/api/sessions/${q(id)}/frames?node=${q(n.node)}&since=${since}&limit=${Math.min(SESSION_PAGE, want - since)}`);
      if (!block.frames.length) break;
      onBlock(n, block);
      done += block.frames.length;
      since = block.cursor;
      progress(total ? done / total : 1);
    }
  }
  progress(1);
  return nodes;
}
