"""Answers from rollups: a DCU's statistics over days or months, and its per-stage history.

:func:`summary` merges a node's rollups of ``since..until``: whole hours from the hour rows, the
minutes at either end from the minute rows (so a month reads about 720 rows a stage, not 43,200),
all its runs together. Counts, means, minimum, maximum, drops, incomplete frames and lost events are
exact (sums of the rows'); percentiles come from the sketch, within ``ALPHA`` of the value
(:mod:`dcuscope.relay.rollup.sketch`). :func:`history` gives per stage a point per minute or hour (p50, p99,
frames), a time without frames having no point: a gap. Both count, besides, the frames that start in
batches not compacted yet (:mod:`dcuscope.relay.store.unrolled`), and say which minutes those were
(``raw``): what ``stats --session`` counts from the same store.
"""

from __future__ import annotations

import json
from pathlib import Path

from dcuscope.relay.errors import RelayError
from dcuscope.relay.rollup.compute import FRAME_ROW, HOUR_NS, MINUTE_NS, Rollup
from dcuscope.relay.rollup.sketch import ALPHA, Sketch
from dcuscope.relay.store.base import Database, stored_rollup
from dcuscope.relay.store.engines import open_database
from dcuscope.relay.store.unrolled import Raw, with_raw

QUANTILES = (("p50_ms", 0.50), ("p90_ms", 0.90), ("p99_ms", 0.99))
EXACT = ("count", "mean_ms", "min_ms", "max_ms", "drops", "incomplete", "lost")
MAX_POINTS = 2000
"""A history has at most this many points a stage: minutes up to 33 hours, hours beyond."""
UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 7 * 86400}


def parse_duration_ns(text: str) -> int:
    """``30d``, ``12h``, ``90m``, ``45s``, ``2w`` (a number alone: seconds) in ns; RelayError otherwise."""
    t = str(text).strip().lower()
    unit = UNITS.get(t[-1:]) if t[-1:].isalpha() else 1
    number = t[:-1] if t[-1:].isalpha() else t
    try:
        value = float(number)
    except ValueError:
        value = float("nan")
    if unit is None or not 0 < value < 1e6 * 86400:
        raise RelayError(f"a duration is a number and a unit, s, m, h, d or w (e.g. 30d), not {text!r}")
    return int(value * unit * 1e9)


def _rows(database: Database, node: str, since_ns: int, until_ns: int) -> list[tuple]:
    """The rows covering since..until: hours inside, minutes at the ends."""
    since, until = since_ns // MINUTE_NS * MINUTE_NS, until_ns
    first_hour = -(-since // HOUR_NS) * HOUR_NS
    last_hour = until // HOUR_NS * HOUR_NS
    if last_hour - first_hour < 2 * HOUR_NS:
        return database.rollup_rows(node, MINUTE_NS, since, until)
    return (database.rollup_rows(node, MINUTE_NS, since, first_hour)
            + database.rollup_rows(node, HOUR_NS, first_hour, last_hour)
            + database.rollup_rows(node, MINUTE_NS, last_hour, until))


def summary(db: str | Path, node: str, since_ns: int, until_ns: int) -> dict:
    """``node``'s statistics over ``since_ns..until_ns`` (relay time, ns) from its rollups and its raw batches."""
    return span(db, node, since_ns, until_ns, points=False)["summary"]


def history(db: str | Path, node: str, since_ns: int, until_ns: int) -> dict:
    """Per stage, and for the frame end to end, a point per minute, or per hour past MAX_POINTS
    minutes: ``{t_ns, frames, p50_ms, p99_ms, mean_ms}``; no point where no frame started (a gap);
    ``kinds``: each stage's element factory, as the live views have it (the page colours by it);
    ``newest_ns``: the newest event's time (None: unknown)."""
    return span(db, node, since_ns, until_ns)["history"]


def span(db: str | Path, node: str, since_ns: int, until_ns: int, points: bool = True) -> dict:
    """``{summary, history}`` of ``node`` over ``since_ns..until_ns``, its raw batches read once."""
    width = MINUTE_NS if (until_ns - since_ns) // MINUTE_NS <= MAX_POINTS else HOUR_NS
    database = open_database(db, create=False)
    try:
        (rows, line_rows), raw = with_raw(database, node, since_ns, until_ns, lambda: (
            _rows(database, node, since_ns, until_ns),
            database.rollup_rows(node, width, since_ns // width * width, until_ns) if points else []))
        order, kinds = _pipeline(database, node, {r[0] for r in rows} | {k[0] for k in raw.rollups})
        newest = _newest(database, node, until_ns, raw) if points else None
    finally:
        database.close()
    out = {"summary": _summary(node, since_ns, until_ns, rows, raw, order)}
    if points:
        out["history"] = _history(node, since_ns, until_ns, width, line_rows, raw, order, kinds, newest)
    return out


def _newest(database: Database, node: str, until_ns: int, raw: Raw) -> int | None:
    newest = max((t for t in (database.newest_compacted_ns(node, until_ns), raw.newest_ns) if t is not None),
                 default=None)
    return None if newest is None else min(newest, until_ns)


def _summary(node: str, since_ns: int, until_ns: int, rows: list[tuple], raw: Raw, order: dict) -> dict:
    merged: dict[str, Rollup] = {}
    starts = set()
    for stage, start, run, *values in rows:
        r = stored_rollup(values)
        merged[stage] = merged[stage].merge(r) if stage in merged else r
        starts.add(int(start))
    for (stage, width, start), r in raw.rollups.items():
        if width == MINUTE_NS:  # each raw frame once (its hour rollup holds it too)
            merged[stage] = merged[stage].merge(r) if stage in merged else r
            starts.add(start)
    frame = merged.pop(FRAME_ROW, Rollup())
    stages = {name: {**_figures(r.delay), "drops": r.drops, "service": _figures(r.service), "wait": _figures(r.wait)}
              for name, r in sorted(merged.items(), key=lambda kv: order.get(kv[0], (1, kv[0])))}
    return {"node": node, "since_ns": since_ns, "until_ns": until_ns, "rows": len(rows),
            "first_ns": min(starts) if starts else None, "last_ns": max(starts) if starts else None,
            "stages": stages, "frame": {**_figures(frame.delay), "incomplete": frame.incomplete, "lost": frame.lost},
            "exact": list(EXACT), "from_sketch": [q for q, _ in QUANTILES], "relative_error": ALPHA,
            "source": "rollups" + (" and raw batches" if raw.rollups else ""), "raw": raw.view()}


def _history(node: str, since_ns: int, until_ns: int, width: int, rows: list[tuple], raw: Raw, order: dict,
             kinds: dict, newest: int | None) -> dict:
    points: dict[str, dict[int, Sketch]] = {}

    def add(stage: str, start: int, sketch: Sketch) -> None:
        at = points.setdefault(stage, {})
        at[start] = at[start].merge(sketch) if start in at else sketch

    for stage, start, run, _incomplete, _drops, _lost, delay, _service, _wait in rows:
        add(stage, int(start), Sketch.decode(bytes(delay)))
    for (stage, w, start), r in raw.rollups.items():
        if w == width:
            add(stage, start, r.delay)

    def line(at: dict[int, Sketch]) -> list[dict]:
        return [{"t_ns": t, "frames": s.count, "mean_ms": _ms(s.mean_ns), "p50_ms": _ms(s.quantile(0.5)),
                 "p99_ms": _ms(s.quantile(0.99))} for t, s in sorted(at.items()) if s.count]

    frame = points.pop(FRAME_ROW, {})
    stages = {stage: line(points[stage]) for stage in sorted(points, key=lambda s: order.get(s, (1, s)))}
    return {"node": node, "since_ns": since_ns, "until_ns": until_ns, "width_ns": width, "frame": line(frame),
            "stages": {k: v for k, v in stages.items() if v}, "kinds": {k: kinds[k] for k in stages if k in kinds},
            "relative_error": ALPHA, "newest_ns": newest, "raw_minutes": raw.minutes()}


def nodes(db: str | Path) -> list[dict]:
    """Every node with rollups or raw batches (a live DCU before its first compaction, a store a relay
    killed outright left): ``{node, first_ns, last_ns}`` (hours), by name."""
    database = open_database(db, create=False)
    try:
        spans = {n: (a, b) for n, a, b in database.rollup_nodes()}
        for n, a, b in database.raw_nodes():
            a, b = a // HOUR_NS * HOUR_NS, b // HOUR_NS * HOUR_NS
            spans[n] = (min(a, spans[n][0]), max(b, spans[n][1])) if n in spans else (a, b)
    finally:
        database.close()
    return [{"node": n, "first_ns": a, "last_ns": b} for n, (a, b) in sorted(spans.items())]


def _figures(s: Sketch) -> dict:
    out = {"count": s.count, "mean_ms": _ms(s.mean_ns), "min_ms": _ms(s.min_ns if s.count else None),
           "max_ms": _ms(s.max_ns if s.count else None)}
    out.update({name: _ms(s.quantile(q)) for name, q in QUANTILES})
    return out


def _ms(ns: float | None) -> float | None:
    return None if ns is None else ns / 1e6


def _pipeline(database: Database, node: str, stages: set[str]) -> tuple[dict[str, tuple], dict[str, str]]:
    """Each stage's place in the pipeline and its element's factory, from the newest stored run that
    has it (raw retention may have deleted every run: then by name, and no factory)."""
    order: dict[str, tuple] = {}
    kinds: dict[str, str] = {}
    for (header,) in database._rows("SELECT header FROM runs WHERE node = %s ORDER BY first_seen_ns DESC LIMIT 50",
                                    (node,)):
        doc = json.loads(header)
        for k, name in enumerate(doc.get("stages", [])):
            order.setdefault(name, (0, k))
        for name, kind in doc.get("kinds", {}).items():
            kinds.setdefault(name, str(kind))
        if stages <= order.keys():
            break
    return order, kinds
