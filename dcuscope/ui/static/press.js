// Presses under way. A browser fires a click only if the element pressed is still in the page when
// the press ends: a view that rewrites its HTML from a push while a press is inside it loses that
// click (a press lasts ~0.1 s, the figures change every second). Such views wait for the press's end.

let pressedOn = null;
addEventListener("pointerdown", (ev) => { pressedOn = ev.target; }, true);
// A press ends when its button is released, anywhere (the page still hears it), or when the page
// itself loses the focus (not an element of it: their blur comes with every press).
for (const end of ["pointerup", "pointercancel"]) addEventListener(end, () => { pressedOn = null; }, true);
addEventListener("blur", (ev) => { if (ev.target === window) pressedOn = null; });

/** Whether a press began inside `el` and has not ended. */
export function pressedWithin(el) {
  return pressedOn !== null && el.contains(pressedOn);
}
