"""Figure 12 of the paper, redrawn from a streams sweep: per-stage mean delay vs stream count.

    .venv/bin/python benchmarks/plot.py build/streams_sweep.json -o docs/streams_sweep.png

One panel per series (input kind x frame rate x bitrate), one row per input kind, each with a
stacked bar per stream count (the stages in the legend colours of the UI: mux red, infer blue,
tiler yellow, convert green, osd purple; the waits between stages grey) and the A = S/n line;
under each bar the frames/s per stream; inside its foot the share of frames the mux dropped late.
A run that gave no figure is marked "failed" at its place (the reasons are in the sweep's
Markdown, under Notes). Drawn with OpenCV so that the project needs no plotting library.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import CannotRun, run  # noqa: E402

STAGE_COLOURS = {  # BGR
    "mux": (48, 48, 220),
    "infer": (200, 100, 30),
    "tiler": (0, 200, 235),
    "convert": (60, 165, 60),
    "osd": (160, 60, 150),
    "queues": (175, 175, 175),
}
INK = (30, 30, 30)
GRID = (225, 225, 225)
SATURATED = (0, 0, 200)
FONT = cv2.FONT_HERSHEY_SIMPLEX
PANEL_W, PANEL_H = 430, 330
MARGIN_L, MARGIN_R, MARGIN_T, MARGIN_B = 62, 14, 36, 46
HEADER_H = 70


def nice_step(top: float, ticks: int = 5) -> float:
    """A 1, 2 or 5 x 10^k step that splits 0..top into about ``ticks`` intervals."""
    if top <= 0:
        return 1.0
    raw = top / ticks
    base = 10 ** math.floor(math.log10(raw))
    return next(m * base for m in (1, 2, 5, 10) if m * base >= raw)


def series_key(r: dict) -> tuple[str, int, int]:
    return r["kind"], r["fps"], r["bitrate"]


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.45, colour=INK, thick: int = 1,
          anchor: str = "left") -> None:
    (w, h), _ = cv2.getTextSize(text, FONT, scale, thick)
    x, y = org
    if anchor == "center":
        x -= w // 2
    elif anchor == "right":
        x -= w
    cv2.putText(img, text, (int(x), int(y)), FONT, scale, colour, thick, cv2.LINE_AA)


def draw_panel(img: np.ndarray, x0: int, y0: int, results: list[dict], counts: list[int], top: float,
               title: str) -> None:
    """One series: stacked stage bars and the A line, in the PANEL_W x PANEL_H box at (x0, y0)."""
    left, right = x0 + MARGIN_L, x0 + PANEL_W - MARGIN_R
    upper, lower = y0 + MARGIN_T, y0 + PANEL_H - MARGIN_B
    _text(img, title, ((left + right) // 2, y0 + 22), 0.5, thick=1, anchor="center")
    step = nice_step(top)
    y_of = lambda ms: lower - (lower - upper) * min(ms, top) / top  # noqa: E731
    for k in range(int(top / step) + 1):
        y = int(round(y_of(k * step)))
        cv2.line(img, (left, y), (right, y), GRID, 1)
        _text(img, f"{k * step:g}", (left - 6, y + 4), 0.4, anchor="right")
    _text(img, "ms", (x0 + 8, upper - 8), 0.4)
    slot = (right - left) / max(len(counts), 1)
    points = []
    by_count = {r["streams"]: r for r in results}
    for i, n in enumerate(counts):
        cx = left + slot * (i + 0.5)
        _text(img, f"{n} stream{'s' if n > 1 else ''}", (cx, lower + 18), 0.45, anchor="center")
        r = by_count.get(n)
        if r is None or r.get("a_ms") is None:
            _text(img, "-" if r is None else "failed", (cx, lower - 6), 0.4, anchor="center")
            continue
        half = slot * 0.3
        base = 0.0
        parts = [(s, r["stages_ms"].get(s) or 0.0) for s in STAGE_COLOURS if s != "queues"]
        parts.append(("queues", max(r.get("queues_ms") or 0.0, 0.0)))
        for stage, ms in parts:
            if ms <= 0:
                continue
            y_hi, y_lo = y_of(base + ms), y_of(base)
            cv2.rectangle(img, (int(cx - half), int(round(y_hi))), (int(cx + half), int(round(y_lo))),
                          STAGE_COLOURS[stage], -1)
            base += ms
        points.append((int(cx), int(round(y_of(r["a_ms"]))), r))
        sat = r.get("saturated")
        fps = "n/a" if r.get("achieved_fps") is None else f"{r['achieved_fps']:.1f}"
        _text(img, f"{fps} fps{' saturated' if sat else ''}", (cx, lower + 36), 0.38,
              SATURATED if sat else INK, anchor="center")
        late, delivered = sum((r.get("late") or {}).values()), sum((r.get("delivered") or {}).values())
        if late and delivered and base > 0:  # inside the bar's foot: the axis labels leave no room
            _text(img, f"{late / delivered:.0%} late", (cx, lower - 8), 0.42, (255, 255, 255), anchor="center")
    for (xa, ya, _), (xb, yb, _) in zip(points, points[1:]):
        cv2.line(img, (xa, ya), (xb, yb), INK, 2, cv2.LINE_AA)
    for x, y, r in points:
        cv2.circle(img, (x, y), 4, INK, -1, cv2.LINE_AA)
        label = f"{r['a_ms']:.0f}" + (" >" if r["a_ms"] > top else "")
        _text(img, label, (x, max(y - 8, upper - 4)), 0.42, anchor="center")
    cv2.line(img, (left, lower), (right, lower), INK, 1)
    cv2.line(img, (left, upper), (left, lower), INK, 1)


def draw_sweep(results: list[dict], path: str | Path, title: str = "streams sweep") -> np.ndarray:
    """Draw every series of ``results`` (Result dicts of streams_sweep) to the PNG ``path``; return the image."""
    kinds = sorted({r["kind"] for r in results})
    columns = sorted({(r["fps"], r["bitrate"]) for r in results})
    counts = sorted({r["streams"] for r in results}) or [1]
    width = max(PANEL_W * max(len(columns), 1), 760)
    height = HEADER_H + PANEL_H * max(len(kinds), 1)
    img = np.full((height, width, 3), 255, np.uint8)
    _text(img, title, (14, 24), 0.6, thick=2)
    x = 14
    for stage, colour in STAGE_COLOURS.items():
        cv2.rectangle(img, (x, 38), (x + 14, 52), colour, -1)
        _text(img, stage, (x + 19, 50), 0.45)
        x += 30 + cv2.getTextSize(stage, FONT, 0.45, 1)[0][0]
    cv2.line(img, (x, 45), (x + 24, 45), INK, 2, cv2.LINE_AA)
    cv2.circle(img, (x + 12, 45), 4, INK, -1, cv2.LINE_AA)
    _text(img, "A = S/n (mean frame delay, ms)", (x + 30, 50), 0.45)
    for row, kind in enumerate(kinds):
        in_row = [r for r in results if r["kind"] == kind and r.get("a_ms") is not None]
        # One scale per input kind: live streams can wait seconds in the jitter buffer's shadow.
        top = max([r["a_ms"] for r in in_row] + [sum((r["stages_ms"].get(s) or 0) for s in r["stages_ms"])
                                                 for r in in_row] + [1.0]) * 1.12
        top = math.ceil(top / nice_step(top)) * nice_step(top)
        for col, (fps, bitrate) in enumerate(columns):
            rs = [r for r in results if series_key(r) == (kind, fps, bitrate)]
            if rs:
                draw_panel(img, col * PANEL_W, HEADER_H + row * PANEL_H, rs, counts, top,
                           f"{kind}, {fps} fps, {bitrate} kbit/s")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: cannot write the plot")
    return img


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, help="the .json a streams sweep wrote next to its --out")
    parser.add_argument("-o", "--output", type=Path, help="PNG to write (default: the results with .png)")
    args = parser.parse_args(argv)
    try:
        data = json.loads(args.results.read_text())
        results = data["results"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CannotRun(f"cannot read {args.results} as the JSON of a streams sweep: {exc!r}") from exc
    try:
        draw_sweep(results, args.output or args.results.with_suffix(".png"),
                   title=f"dcuscope streams sweep, model {data.get('model', '?')}")
    except OSError as exc:
        raise CannotRun(str(exc)) from exc
    return 0


if __name__ == "__main__":
    raise SystemExit(run(main))
