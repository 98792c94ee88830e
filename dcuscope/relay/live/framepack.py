"""Frames as the relay pushes them to browsers: packed in two binary columns blocks, not one JSON
object per frame.

The pushes carry every frame of every DCU a page shows (a paced DCU completes ~360 a second): built
one Python dict per frame and JSON-encoded, they cost the relay more than pairing them. Packed, a
push's frames are two arrays built with a few numpy calls, sent as Socket.IO binary attachments:

- ``ints``: int64, one row of ``count`` values per field of :data:`INT_FIELDS` (per-stage fields
  one row per stage), row after row; :data:`dcuscope.model.frametable.MISSING` in ``enter``, ``exit`` and
  ``capture`` is a missing time (null);
- ``floats``: float64, the same for :data:`FLOAT_FIELDS`; NaN is a missing figure (null).

Unpacked (:func:`unpack`, and the page's ``unpackFrames`` in ``ui/static/feed.js``), the frames are
exactly those of :func:`dcuscope.relay.live.framejson.frame_dicts`, as ``GET /api/frames`` gives them. The
block says its layout (``int_fields``, ``float_fields``: [name, rows]), so a client needs no table
of its own.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from dcuscope.model import compiled as compiled_core
from dcuscope.model.delays import NS_PER_MS, STAGE_COLUMNS, FrameDelays
from dcuscope.model.frametable import MISSING
from dcuscope.relay.clock.correction import Correction

PER_STAGE = "stage"
INT_FIELDS = (("n", 1), ("source", 1), ("frame", 1), ("origin", 1), ("end", 1), ("complete", 1), ("enter", PER_STAGE),
              ("exit", PER_STAGE), ("capture", 1), ("clock_ns", 1), ("clock_uncertainty_ns", 1))
FLOAT_FIELDS = (("delay_ms", 1), ("glass_ms", 1), *((f"stage_{c}_ms", PER_STAGE) for c in STAGE_COLUMNS))
NULLABLE_INTS = ("enter", "exit", "capture")
"""Int fields where MISSING means no time (null); elsewhere -1 is a value (an offset)."""
BOOLS = ("complete",)
PER_STAGE_NAMES = {name for name, rows in INT_FIELDS + FLOAT_FIELDS if rows == PER_STAGE}


def columns(n: np.ndarray, fd: FrameDelays, corr: Correction) -> tuple[np.ndarray, np.ndarray]:
    """The frames of ``fd`` (``n`` the cursor of each) as (ints, floats), fields in the order of
    :data:`INT_FIELDS` and :data:`FLOAT_FIELDS`, each of shape (rows, frames); the same values as
    :func:`dcuscope.relay.live.framejson.frame_dicts` (every node time moved by ``corr`` at the frame's origin)."""
    return corrected(*node_columns(n, fd), corr, fd.table.enter.shape[1])


def node_columns(n: np.ndarray, fd: FrameDelays) -> tuple[np.ndarray, np.ndarray]:
    """:func:`columns` as the node's clock has them, floats in ns: what the live engine keeps of the
    frames it shows, moved and scaled only when pushed (:func:`corrected`)."""
    t, ch = fd.table, fd.chains
    zero = np.zeros(len(t), np.int64)
    ints = np.concatenate([
        np.stack([np.asarray(n, np.int64), t.source.astype(np.int64), t.frame.astype(np.int64), t.origin, ch.end,
                  ch.complete.astype(np.int64)]),
        t.enter.T, t.exit.T, np.stack([t.capture.astype(np.int64), zero, zero]),
    ]).astype(np.int64, copy=False)
    floats = np.concatenate([np.stack([fd.delay, fd.glass]), *(fd.per_stage[c].T for c in STAGE_COLUMNS)])
    return ints, floats


def corrected(ints: np.ndarray, floats: np.ndarray, corr: Correction, stages: int, *,
              compiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Columns of :func:`node_columns` with every node time moved by ``corr`` at the frame's origin,
    and the floats in ms (new arrays, field-major): in one compiled pass where the compiled core loads
    and the columns are kept a frame a row (the live engine's, :meth:`LiveRun.recent_columns`), else
    with numpy (:func:`corrected_numpy`, the reference)."""
    core = compiled_core.load() if compiled else None
    if core is None or not (ints.flags.f_contiguous and floats.flags.f_contiguous) or ints.dtype != np.int64 \
            or floats.dtype != np.float64:
        return corrected_numpy(ints, floats, corr, stages)
    k = ints.shape[1]
    out_ints, out_floats = np.empty(ints.shape, np.int64), np.empty(floats.shape)
    at = corr.segment_addresses if corr.segments else (None,) * 6
    core.push_columns(ints.ctypes.data, floats.ctypes.data, k, stages, *at, len(corr.segments), corr.base_uncertainty_ns,
                      out_ints.ctypes.data, out_floats.ctypes.data)
    return out_ints, out_floats


def corrected_numpy(ints: np.ndarray, floats: np.ndarray, corr: Correction, stages: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`corrected` with numpy, a field at a time."""
    rows = _rows(INT_FIELDS, stages)
    times, keep = _times(stages)
    origin, end = ints[rows["origin"]][0], ints[rows["end"]][0]
    fc = corr.per_frame(origin)
    out = ints.copy()
    moved = fc.correct(ints[times], columns=True)
    out[times] = moved
    out[keep] = ints[keep]
    out[rows["clock_ns"]] = origin - moved[0]  # the offsets at the origins (the first of the times' rows)
    out[rows["clock_uncertainty_ns"]] = fc.uncertainties(origin)
    floats = floats.copy()
    floats[_rows(FLOAT_FIELDS, stages)["glass_ms"]] -= fc.offsets(end).astype(np.float64)
    return out, floats / NS_PER_MS


@lru_cache(maxsize=64)
def _times(stages: int) -> tuple[slice, slice]:
    """The rows of the int fields that are node times, as one slice from the first to the last,
    and the rows inside it that are not (kept as they are)."""
    rows = _rows(INT_FIELDS, stages)
    assert [name for name, _ in INT_FIELDS[3:8]] == ["origin", "end", "complete", "enter", "exit"]
    return slice(rows["origin"].start, rows["exit"].stop), rows["complete"]


@lru_cache(maxsize=64)
def _rows(fields: tuple, stages: int) -> dict[str, slice]:
    """Where each field's rows are in a columns array."""
    out, row = {}, 0
    for name, rows in _layout(fields, stages):
        out[name] = slice(row, row + rows)
        row += rows
    return out


def packed(ints: np.ndarray, floats: np.ndarray, stages: int, last: int | None = None) -> dict:
    """The ``packed`` entry of a pushed block: the columns' bytes (their ``last`` frames only, if given)."""
    if last is not None and ints.shape[1] > last:
        ints, floats = ints[:, -last:], floats[:, -last:]
    return {"count": int(ints.shape[1]), "stages": stages, "int_fields": _layout(INT_FIELDS, stages),
            "float_fields": _layout(FLOAT_FIELDS, stages), "ints": np.ascontiguousarray(ints, "<i8").tobytes(),
            "floats": np.ascontiguousarray(floats, "<f8").tobytes()}


def unpack(block: dict) -> dict:
    """``block`` with its ``packed`` frames as ``frames`` (dicts, as ``GET /api/frames``); a block
    without ``packed`` as it is. For Python clients of the pushes (tests)."""
    p = block.get("packed")
    if p is None:
        return block
    ints, floats = columns_of(p)
    fields: dict[str, list] = {}
    for name, part in [*ints.items(), *floats.items()]:
        rows = part.T.tolist()  # one list per frame
        if name in NULLABLE_INTS:
            rows = [[None if v == MISSING else v for v in r] for r in rows]
        elif name in BOOLS:
            rows = [[bool(v) for v in r] for r in rows]
        elif part.dtype.kind == "f":
            rows = [[None if v != v else v for v in r] for r in rows]
        fields[name] = rows if name in PER_STAGE_NAMES else [r[0] for r in rows]
    out = {key: value for key, value in block.items() if key != "packed"}
    out["frames"] = [{name: values[i] for name, values in fields.items()} for i in range(p["count"])]
    return out


def columns_of(p: dict) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The ``packed`` entry's fields as arrays, (ints, floats): name -> (rows, count)."""
    k = p["count"]
    out = []
    for key, layout, dtype in (("ints", p["int_fields"], "<i8"), ("floats", p["float_fields"], "<f8")):
        matrix = np.frombuffer(p[key], dtype).reshape(-1, k) if k else np.zeros((sum(r for _, r in layout), 0), dtype)
        fields, row = {}, 0
        for name, rows in layout:
            fields[name] = matrix[row:row + rows]
            row += rows
        out.append(fields)
    return out[0], out[1]


def unpack_push(msg: dict) -> dict:
    """A ``frames`` push with every block's frames unpacked (:func:`unpack`)."""
    return dict(msg, nodes={node: unpack(block) for node, block in msg["nodes"].items()})


def int_rows(stages: int) -> int:
    """Rows of an ints columns array for ``stages`` stages."""
    return sum(r for _, r in _layout(INT_FIELDS, stages))


def float_rows(stages: int) -> int:
    """Rows of a floats columns array for ``stages`` stages."""
    return sum(r for _, r in _layout(FLOAT_FIELDS, stages))


def _layout(fields: tuple, stages: int) -> list[list]:
    return [[name, stages if rows == PER_STAGE else rows] for name, rows in fields]
