// Time and delay formatting, axis ticks: pure functions (tests/ui/test_page_units.py).
// Times are milliseconds since the epoch on the relay's clock (Float64: ~0.2 µs resolution).

const STEPS_MS = [];
for (let decade = 1; decade <= 1e7; decade *= 10) {
  for (const m of [1, 2, 5]) STEPS_MS.push(m * decade);
}
// Round steps of the clock beyond a few seconds: 10 s, 15 s, 30 s, 1 min, ...
const CLOCK_STEPS_MS = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000, 15000, 30000,
  60000, 120000, 300000, 600000, 900000, 1800000, 3600000];

const pad = (n, w) => String(n).padStart(w, "0");

/** "HH:MM:SS.mmm" of a time in ms since the epoch, in the browser's time zone. */
export function formatClock(ms) {
  const whole = Math.floor(ms);
  const d = new Date(whole);
  return `${pad(d.getHours(), 2)}:${pad(d.getMinutes(), 2)}:${pad(d.getSeconds(), 2)}.${pad(d.getMilliseconds(), 3)}`;
}

/** "HH:MM:SS.mmmuuu": the clock to the microsecond, for tooltips. */
export function formatClockPrecise(ms) {
  const us = Math.floor((ms - Math.floor(ms)) * 1000);
  return `${formatClock(ms)}${pad(us, 3)}`;
}

/** A delay for people: "850 µs", "12.35 ms", "1.234 s". */
export function formatDelay(ms) {
  if (ms === null || ms === undefined || Number.isNaN(ms)) return "–";
  const a = Math.abs(ms);
  if (a < 1) return `${(ms * 1000).toFixed(0)} µs`;
  if (a < 1000) return `${ms.toFixed(a < 100 ? 2 : 1)} ms`;
  return `${(ms / 1000).toFixed(3)} s`;
}

/**
 * A clock offset and its bound (ms) in one unit, the larger one's: {offset: "−1.0 µs", bound: "± 5.1 µs"},
 * {offset: "+3.012 ms", bound: "± 0.051 ms"} (two units side by side read as two scales). `bound`
 * is "" where unknown (NaN); an offset that rounds to 0 has no sign ("−0" reads as a fault).
 */
export function formatOffsetBound(offsetMs, boundMs) {
  const known = Number.isFinite(boundMs);
  const big = Math.max(Math.abs(offsetMs), known ? Math.abs(boundMs) : 0);
  const [scale, unit, digits] = big < 1 ? [1000, "µs", big < 0.01 ? 1 : 0] : big < 1000 ? [1, "ms", 3] : [0.001, "s", 6];
  const text = (ms) => `${(Math.abs(ms) * scale).toFixed(digits)} ${unit}`;
  const zero = Number((Math.abs(offsetMs) * scale).toFixed(digits)) === 0;
  return { offset: `${zero ? "" : offsetMs >= 0 ? "+" : "−"}${text(offsetMs)}`, bound: known ? `± ${text(boundMs)}` : "" };
}

/** The smallest step of `steps` that is at least `minMs`, else the largest. */
function stepAtLeast(steps, minMs) {
  for (const s of steps) if (s >= minMs) return s;
  return steps[steps.length - 1];
}

/**
 * Ticks of a clock axis over [t0, t1] drawn `widthPx` wide: labelled ticks at least `minPx`
 * apart on round clock values (1, 2, 5 ms ... 1 h), unlabelled minor ticks between them.
 */
export function clockTicks(t0, t1, widthPx, minPx = 110) {
  const span = Math.max(t1 - t0, 1e-6);
  const step = stepAtLeast(CLOCK_STEPS_MS, (span / Math.max(widthPx, 1)) * minPx);
  const minor = step / (String(step)[0] === "2" ? 4 : 5);
  const major = [];
  const minors = [];
  // Ticks on multiples of the step in local time, so "12:00:00.000" lands on a tick.
  const tz = new Date(t0).getTimezoneOffset() * 60000;
  const first = Math.ceil((t0 - tz) / step) * step + tz;
  for (let t = first; t <= t1 && major.length < 1000; t += step) major.push(t);
  const firstMinor = Math.ceil((t0 - tz) / minor) * minor + tz;
  for (let t = firstMinor; t <= t1 && minors.length < 5000; t += minor) minors.push(t);
  return { step, major, minor: minors };
}

/** A delay axis label: "0", "250 µs", "20 ms", "1.5 s" (no needless decimals). */
export function formatTick(ms) {
  if (ms === 0) return "0";
  const trim = (v) => String(Number(v.toPrecision(6)));
  if (ms < 1) return `${trim(ms * 1000)} µs`;
  if (ms < 1000) return `${trim(ms)} ms`;
  return `${trim(ms / 1000)} s`;
}

/** Ticks of a delay axis over [0, maxMs]: values on 1-2-5 steps at least `minPx` apart. */
export function delayTicks(maxMs, widthPx, minPx = 70) {
  const step = stepAtLeast(STEPS_MS.map((s) => s / 1000), (maxMs / Math.max(widthPx, 1)) * minPx);
  const out = [];
  for (let v = 0; v <= maxMs + 1e-9 && out.length < 1000; v += step) out.push(Number(v.toFixed(6)));
  return { step, values: out };
}

/** A round upper bound for a delay axis: 1, 2, 2.5, 5 x 10^k at or above `ms`. */
export function niceCeil(ms) {
  if (!(ms > 0)) return 1;
  const p = 10 ** Math.floor(Math.log10(ms));
  for (const m of [1, 2, 2.5, 5, 10]) if (m * p >= ms - 1e-12) return m * p;
  return 10 * p;
}
