// Zoomed out, a stage's bars get narrower than a pixel. Drawn at a minimum width, a 0.3 ms stage
// would look as busy as a 100 ms one; instead each pixel column shows the fraction of its time
// that the stage's frames covered (their union: a batch's frames share one service interval,
// which counts once).

/**
 * Where a frame's service begins in its bar [enter, exit]: the stage waits, then works, then the
 * frame exits, so the last `service` ms are service and the ones before are wait. Service
 * unknown (NaN: old traces, Python probes) counts as the whole bar, which is drawn solid as ever.
 */
export function serviceStart(enter, exit, service) {
  if (!(service >= 0)) return enter;
  return Math.max(enter, Math.min(exit, exit - service));
}

/** Growable scratch for interval ends, so that drawing allocates nothing once warm. */
export class Intervals {
  constructor(capacity = 1024) {
    this.starts = new Float64Array(capacity);
    this.ends = new Float64Array(capacity);
    this.n = 0;
  }

  clear() {
    this.n = 0;
  }

  /** Add [a, b); empty ones are no time and are left out. */
  add(a, b) {
    if (!(b > a)) return;
    if (this.n === this.starts.length) {
      const starts = new Float64Array(this.n * 2);
      const ends = new Float64Array(this.n * 2);
      starts.set(this.starts);
      ends.set(this.ends);
      this.starts = starts;
      this.ends = ends;
    }
    this.starts[this.n] = a;
    this.ends[this.n] = b;
    this.n++;
  }
}

/**
 * Per pixel column of [t0, t1] split into `columns` equal columns, the fraction (0..1) of the
 * column's time inside the union of `iv`'s intervals, in any order. Sorting starts and ends
 * apart is enough to sweep the union (the k-th smallest end is past the k-th smallest start),
 * and a typed array sorts without a comparator.
 */
export function columnCoverage(iv, t0, t1, columns, out = new Float32Array(columns)) {
  out.fill(0);
  const n = iv.n;
  if (!n || !(t1 > t0) || columns <= 0) return out;
  const starts = sortNearly(iv.starts.subarray(0, n));
  const ends = sortNearly(iv.ends.subarray(0, n));
  const cw = (t1 - t0) / columns;
  let active = 0;
  let open = 0;
  for (let i = 0, j = 0; j < n;) {
    if (i < n && starts[i] < ends[j]) {
      if (active++ === 0) open = starts[i];
      i++;
    } else {
      if (--active === 0) addSpan(out, Math.max(open, t0), Math.min(ends[j], t1), t0, cw, columns);
      j++;
    }
  }
  for (let c = 0; c < columns; c++) out[c] = Math.min(1, out[c] / cw);
  return out;
}

/** Add the time of [a, b) (inside the window) to the columns it crosses, in ms. */
function addSpan(out, a, b, t0, cw, columns) {
  if (!(b > a)) return;
  const ca = Math.min(columns - 1, Math.floor((a - t0) / cw));
  const cb = Math.min(columns - 1, Math.floor((b - t0) / cw));
  if (ca === cb) {
    out[ca] += b - a;
    return;
  }
  out[ca] += t0 + (ca + 1) * cw - a;
  for (let c = ca + 1; c < cb; c++) out[c] += cw;
  out[cb] += b - (t0 + cb * cw);
}

/**
 * Sort `a` in place. A lane's frames come nearly in time order (as the relay completes them),
 * which an insertion sort puts right in about one pass; past a budget of moves (data far from
 * sorted) the native sort takes over.
 */
export function sortNearly(a) {
  let budget = 4 * a.length;
  for (let i = 1; i < a.length; i++) {
    const v = a[i];
    let j = i - 1;
    while (j >= 0 && a[j] > v) {
      a[j + 1] = a[j];
      j--;
      if (--budget < 0) {
        a[j + 1] = v; // the slot left free: nothing lost, nothing doubled
        return a.sort();
      }
    }
    a[j + 1] = v;
  }
  return a;
}
