// The fleet overview's height while DCUs are opened: a grip under the table sets it (drag, or the
// up and down keys), a double-click forgets it, and the page remembers it (localStorage) across
// reloads. It is a maximum: a fleet of fewer rows takes less. With no DCU opened the stylesheet
// lets the overview take the screen instead (body.fleet-only), whatever was chosen here.

export const HEIGHT_KEY = "dcuscope.overviewHeight";
export const MIN_HEIGHT = 60; // px: the head and about two rows
export const KEY_STEP = 24; // px per up or down key: about one row

/** A stored height as a number of px, or null (none, or not one the grip could have set). */
export function parseHeight(text) {
  const h = Number(text);
  return text !== null && text !== "" && Number.isFinite(h) && h >= MIN_HEIGHT ? Math.round(h) : null;
}

function stored(storage) {
  try {
    return parseHeight(storage.getItem(HEIGHT_KEY));
  } catch (_) {
    return null; // storage refused (a private window's quota, a sandbox): the default
  }
}

function store(storage, px) {
  try {
    if (px === null) storage.removeItem(HEIGHT_KEY);
    else storage.setItem(HEIGHT_KEY, String(px));
  } catch (_) {
    // not kept past this page: nothing else to do
  }
}

/** Wire `grip` to set `wrap`'s height; the height chosen before is applied at once. */
export function installGrip(wrap, grip, storage = window.localStorage) {
  const apply = (px) => {
    wrap.style.maxHeight = px === null ? "" : `${px}px`;
  };
  const choose = (px) => {
    const h = px === null ? null : Math.max(MIN_HEIGHT, Math.round(px));
    apply(h);
    store(storage, h);
  };
  apply(stored(storage));

  grip.addEventListener("pointerdown", (ev) => {
    if (ev.button !== 0) return;
    ev.preventDefault();
    grip.setPointerCapture(ev.pointerId);
    const y0 = ev.clientY;
    const h0 = wrap.getBoundingClientRect().height;
    const move = (e) => apply(Math.max(MIN_HEIGHT, Math.round(h0 + e.clientY - y0)));
    const up = (e) => {
      grip.removeEventListener("pointermove", move);
      grip.removeEventListener("pointerup", up);
      grip.removeEventListener("pointercancel", up);
      choose(h0 + e.clientY - y0);
    };
    grip.addEventListener("pointermove", move);
    grip.addEventListener("pointerup", up);
    grip.addEventListener("pointercancel", up);
  });
  grip.addEventListener("dblclick", () => choose(null));
  grip.addEventListener("keydown", (ev) => {
    const step = ev.key === "ArrowDown" ? KEY_STEP : ev.key === "ArrowUp" ? -KEY_STEP : 0;
    if (!step) return;
    ev.preventDefault();
    choose(wrap.getBoundingClientRect().height + step);
  });
}
