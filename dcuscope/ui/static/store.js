// Bounded, columnar frame storage per node: typed-array rings, so the page's memory stays flat
// however long it runs, and drawing walks numbers, not objects.

export const LIVE_CAPACITY = 65536; // frames per node kept whole (3 min at 6 x 60 fps)
export const DELAY_CAPACITY = 1 << 20; // frame delays per node kept for the over-limit counts

/**
 * The last `capacity` frame delays a page received for a DCU and how many exceed `limit` (null: no
 * limit, none counted), kept up to date on push; `since` is the origin (ms) of the first one, until
 * the ring wraps (`wrapped`: from then on it holds the last `capacity`); `firstN`, the first one's
 * cursor in its run (1: the run's first frame; more: the relay no longer kept the earlier ones).
 */
export class DelayRing {
  constructor(capacity = DELAY_CAPACITY, limit = null) {
    this.values = new Float32Array(capacity);
    this.capacity = capacity;
    this.head = 0;
    this.size = 0;
    this.limit = limit;
    this.over = 0;
    this.since = null;
    this.firstN = null;
    this.wrapped = false;
  }

  push(ms, origin = null, n = null) {
    const limit = this.limit;
    if (this.size === this.capacity) {
      if (limit !== null && this.values[this.head] > limit) this.over--;
      this.values[this.head] = ms;
      this.head = (this.head + 1) % this.capacity;
      this.wrapped = true;
    } else {
      if (this.size === 0 && this.since === null) {
        this.since = origin;
        this.firstN = n;
      }
      this.values[(this.head + this.size) % this.capacity] = ms;
      this.size++;
    }
    if (limit !== null && ms > limit) this.over++;
  }

  setLimit(limit) {
    this.limit = limit;
    let over = 0;
    if (limit !== null) {
      const v = this.values;
      for (let i = 0; i < this.size; i++) if (v[(this.head + i) % this.capacity] > limit) over++;
    }
    this.over = over;
  }
}

export class NodeStore {
  /**
   * Frames of one node (one run, or consecutive runs with the same stages), oldest evicted
   * first. Times are ms since the epoch (relay clock); a missing tracepoint is NaN.
   */
  constructor(node, stages, capacity = LIVE_CAPACITY, delayCapacity = DELAY_CAPACITY, limit = null) {
    this.node = node;
    this.capacity = capacity;
    this.delays = new DelayRing(delayCapacity, limit);
    this.run = null;
    this.reset(stages);
  }

  reset(stages) {
    const cap = this.capacity;
    this.stages = [...stages];
    this.S = this.stages.length;
    this.source = new Int32Array(cap);
    this.frame = new Float64Array(cap);
    this.origin = new Float64Array(cap);
    this.end = new Float64Array(cap);
    this.delay = new Float32Array(cap);
    this.enter = new Float64Array(cap * this.S);
    this.exit = new Float64Array(cap * this.S);
    this.stageDelay = new Float64Array(cap * this.S); // ms, NaN where the frame has none
    // delay = service (the stage's own work on the frame or its batch) + wait; NaN where unknown.
    this.stageService = new Float32Array(cap * this.S);
    this.stageWait = new Float32Array(cap * this.S);
    this.maxEnd = new Float64Array(cap); // running maximum of `end` in arrival order: searchable
    // What the relay subtracted from the frame's node timestamps at its origin (ms: raw = corrected
    // + clock), and its bound (ms, NaN where the relay sent none).
    this.clock = new Float64Array(cap);
    this.clockBound = new Float64Array(cap);
    this.clockMin = 0; // smallest and largest `clock` ever held: how far raw times may lie from corrected ones
    this.clockMax = 0;
    this.clockApplied = null; // the relay's correction of the newest block: estimate, ptp, none, ...
    this.head = 0;
    this.size = 0;
    this.lastN = 0;
    this.received = 0;
    this.newestEnd = -Infinity;
    this.barStage = new Uint8Array(this.S); // 1 where the relay says the stage has an exit point: a lane
    this.sourceCounts = new Map();
    this._sources = null;
    this.version = 0;
    this.delays.setLimit(this.delays.limit);
  }

  /** Physical slot of logical index i (0 = oldest). */
  slot(i) {
    return (this.head + i) % this.capacity;
  }

  /** Sources seen, sorted. */
  get sources() {
    if (this._sources === null) this._sources = [...this.sourceCounts.keys()].sort((a, b) => a - b);
    return this._sources;
  }

  /** Lanes: indices of the stages that have bars, in pipeline order. */
  get lanes() {
    const out = [];
    for (let s = 0; s < this.S; s++) if (this.barStage[s]) out.push(s);
    return out;
  }

  /**
   * Add a block shaped as GET /api/frames ({run, stages, has_exit[], clock, frames: [{n, source, frame,
   * origin, end, enter[], exit[], delay_ms, stage_delay_ms[], stage_service_ms[]?, stage_wait_ms[]?,
   * clock_ns, clock_uncertainty_ns}]}); frames at or below the cursor
   * already held are skipped. Every figure comes from the relay; none is derived here.
   * Returns how many were added.
   */
  ingest(block) {
    if (block.run !== this.run) {
      const same = block.stages.length === this.S && block.stages.every((s, i) => s === this.stages[i]);
      if (!same) this.reset(block.stages);
      this.run = block.run;
      this.lastN = 0;
    }
    (block.has_exit ?? []).forEach((h, s) => { if (h && s < this.S) this.barStage[s] = 1; });
    if (block.clock !== undefined) this.clockApplied = block.clock;
    let added = 0;
    for (const f of block.frames) {
      if (f.n <= this.lastN) continue;
      this.lastN = f.n;
      this.push(f);
      added++;
    }
    if (added) this.version++;
    return added;
  }

  push(f) {
    const cap = this.capacity;
    let p;
    if (this.size === cap) {
      p = this.head;
      this.head = (this.head + 1) % cap;
    } else {
      p = (this.head + this.size) % cap;
      this.size++;
    }
    const S = this.S;
    const origin = f.origin / 1e6;
    const end = f.end / 1e6;
    this.source[p] = f.source;
    this.frame[p] = f.frame;
    this.origin[p] = origin;
    this.end[p] = end;
    this.delay[p] = f.delay_ms;
    const clock = (f.clock_ns ?? 0) / 1e6;
    this.clock[p] = clock;
    this.clockBound[p] = f.clock_uncertainty_ns === null || f.clock_uncertainty_ns === undefined ? NaN : f.clock_uncertainty_ns / 1e6;
    this.clockMin = Math.min(this.clockMin, clock);
    this.clockMax = Math.max(this.clockMax, clock);
    const base = p * S;
    for (let s = 0; s < S; s++) {
      const a = f.enter[s];
      const b = f.exit[s];
      this.enter[base + s] = a === null || a === undefined ? NaN : a / 1e6;
      this.exit[base + s] = b === null || b === undefined ? NaN : b / 1e6;
      this.stageDelay[base + s] = f.stage_delay_ms?.[s] ?? NaN;
      this.stageService[base + s] = f.stage_service_ms?.[s] ?? NaN;
      this.stageWait[base + s] = f.stage_wait_ms?.[s] ?? NaN;
    }
    this.newestEnd = Math.max(this.newestEnd, end);
    this.maxEnd[p] = this.newestEnd;
    const c = this.sourceCounts.get(f.source);
    if (c === undefined) this._sources = null;
    this.sourceCounts.set(f.source, (c ?? 0) + 1);
    this.delays.push(f.delay_ms, origin, f.n ?? null);
    this.received++;
  }

  /** First logical index whose running-maximum end is >= t (earlier frames all ended before t). */
  firstEndingAfter(t) {
    let lo = 0;
    let hi = this.size;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (this.maxEnd[this.slot(mid)] < t) lo = mid + 1;
      else hi = mid;
    }
    return lo;
  }

  /** First logical index whose running-maximum end is > t (frames from there on end after t). */
  firstEndingBeyond(t) {
    let lo = 0;
    let hi = this.size;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (this.maxEnd[this.slot(mid)] <= t) lo = mid + 1;
      else hi = mid;
    }
    return lo;
  }

  /** [oldest origin, newest end] held, or null. */
  span() {
    if (!this.size) return null;
    let first = Infinity;
    for (let i = 0; i < Math.min(this.size, 4096); i++) first = Math.min(first, this.origin[this.slot(i)]);
    return [first, this.newestEnd];
  }
}
