// Stage colours: the paper's legend for the five DeepStream-like stages, a palette for the rest.

export const STAGE_COLOURS = Object.freeze({
  mux: "#e53935", // red: frame collection (nvstreammux)
  infer: "#1e88e5", // blue: neural network (nvinfer)
  tiler: "#fdd835", // yellow: collage (nvmultistreamtiler)
  convert: "#43a047", // green: post-inference processing (nvvideoconvert)
  osd: "#8e24aa", // purple: on-screen display (nvdsosd)
});

// Elements inserted by a configuration (queues, a second infer named otherwise, ...): colours
// far from the five above, assigned in order of appearance so every DCU shows a stage alike.
export const PALETTE = Object.freeze(["#fb8c00", "#00897b", "#6d4c41", "#d81b60", "#546e7a",
  "#c0ca33", "#00acc1", "#3949ab", "#f4511e", "#7cb342"]);

export const OVER_LIMIT = "#8b0000"; // deep red: a frame slower than the limit
export const UNDER_LIMIT = "#78909c";
export const LIMIT_LINE = "#ff1744";

export const WAIT_TINT = 0.3; // a stage's wait: its colour at 30 % over white, service solid

/** `hex` (#rrggbb) at `alpha` over white, as an opaque #rrggbb: bars stay on whole, unblended pixels. */
export function tint(hex, alpha = WAIT_TINT) {
  const v = parseInt(hex.slice(1), 16);
  const mix = (shift) => Math.round(255 - alpha * (255 - ((v >> shift) & 255)));
  return `#${((mix(16) << 16) | (mix(8) << 8) | mix(0)).toString(16).padStart(6, "0")}`;
}

/** "infer_2" -> "infer": stage names are element names, de-duplicated with _N. */
export function baseName(stage) {
  return String(stage).replace(/_\d+$/, "");
}

export class StageColours {
  constructor() {
    this.assigned = new Map();
    this.kinds = new Map();
    this.next = 0;
  }

  /**
   * Stage name -> element factory, from a node's trace header ({pgie: "infer"}): a stage is
   * coloured by what its element is, whatever it is called. Learnt before its first use.
   */
  learn(kinds) {
    for (const [stage, factory] of Object.entries(kinds ?? {})) {
      if (this.kinds.has(stage)) continue;
      this.kinds.set(stage, factory);
      const colour = STAGE_COLOURS[factory];
      if (colour !== undefined && this.assigned.has(stage) && this.assigned.get(stage) !== colour) {
        this.assigned.set(stage, colour); // it was seen before its kind was known
      }
    }
  }

  get(stage) {
    let colour = this.assigned.get(stage);
    if (colour === undefined) {
      colour = STAGE_COLOURS[this.kinds.get(stage)] ?? STAGE_COLOURS[baseName(stage)]
        ?? PALETTE[this.next++ % PALETTE.length];
      this.assigned.set(stage, colour);
    }
    return colour;
  }

  /** Whether `stage` has its colour yet (a view of stored data colours the others apart: the legend stays the live one). */
  has(stage) {
    return this.assigned.has(stage);
  }

  /** [[stage, colour]] in order of first use: the legend. */
  entries() {
    return [...this.assigned.entries()];
  }
}

/**
 * The legend: [[stage, colour]] of the stages the shown DCUs draw bars for (their lanes), in order of
 * first use. Only theirs: a stage another DCU has (a queue) is not listed beside a DCU without it.
 */
export function legendEntries(colours, stores) {
  const shown = new Set();
  for (const store of stores) for (const lane of store.lanes) shown.add(store.stages[lane]);
  return colours.entries().filter(([stage]) => shown.has(stage));
}
