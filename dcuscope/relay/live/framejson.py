"""Frames as the API and the UI carry them: one JSON object per complete frame, built here only.

Per frame::

    {"n": cursor, "source", "frame", "origin": ns, "end": ns, "complete": true,
     "enter": [ns|null per stage], "exit": [ns|null per stage], "delay_ms": end - origin,
     "stage_delay_ms": [ms|null per stage], "stage_gap_ms": [ms|null per stage],
     "stage_service_ms": [...], "stage_wait_ms": [...],
     "capture": ns|null (the camera's clock: never corrected), "glass_ms": corrected end - capture|null,
     "clock_ns": offset subtracted at the origin, "clock_uncertainty_ns": its bound}

one ``stage_<column>_ms`` list per column of the delay model (``model.delays.STAGE_COLUMNS``),
every figure taken from it, so that the page only draws. Timestamps are moved to the relay's
clock by the run's correction (:class:`dcuscope.relay.clock.correction.Correction`, per timestamp, by the estimate in
force at the frame's origin). A block adds the node, run, stages, their kinds, ``has_exit``
(per stage: it has an exit point, so its frames have bars), the clock and the paging cursor.
"""

from __future__ import annotations

import numpy as np

from dcuscope.model.delays import NS_PER_MS, STAGE_COLUMNS, FrameDelays
from dcuscope.model.frametable import MISSING
from dcuscope.relay.clock.correction import Correction


def frame_dicts(n: np.ndarray, fd: FrameDelays, corr: Correction, rows: np.ndarray | None = None) -> list[dict]:
    """One dict per row of ``fd`` (or per index in ``rows``), ``n`` the cursor of each; every node
    timestamp moved by ``corr`` (per timestamp), each frame with the offset subtracted at its
    origin (``clock_ns``) and its bound (``clock_uncertainty_ns``)."""
    rows = np.arange(len(fd)) if rows is None else rows
    t, ch = fd.table, fd.chains
    columns = {f"stage_{c}_ms": _ms_lists(fd.per_stage[c][rows]) for c in STAGE_COLUMNS}
    origin, end = t.origin[rows], ch.end[rows]
    # Every time of a frame by the estimate in force at its origin: a new estimate arriving while
    # the frame went through the pipeline leaves its delays as measured.
    enter, exit_ = t.enter[rows], t.exit[rows]
    per_stage = np.broadcast_to(origin[:, None], enter.shape)
    # The capture time is the camera's clock (RTCP sender reports), not the node's: it is left as
    # it is, and glass-to-glass is taken from the node's corrected end.
    glass = fd.glass[rows] - corr.offsets(end, origin).astype(np.float64)
    base = zip(np.asarray(n).tolist(), t.source[rows].tolist(), t.frame[rows].tolist(), corr.correct(origin).tolist(),
               corr.correct(end, origin).tolist(), ch.complete[rows].tolist(),
               _lists(corr.correct(enter, per_stage)), _lists(corr.correct(exit_, per_stage)),
               _ms_values(fd.delay[rows]), t.capture[rows].tolist(),
               _ms_values(glass), corr.offsets(origin).tolist(), corr.uncertainties(origin).tolist())
    return [
        {"n": k, "source": s, "frame": f, "origin": o, "end": e, "complete": c, "enter": en, "exit": ex, "delay_ms": d,
         "capture": None if cap == MISSING else cap, "glass_ms": g, "clock_ns": off, "clock_uncertainty_ns": unc,
         **{name: values[i] for name, values in columns.items()}}
        for i, (k, s, f, o, e, c, en, ex, d, cap, g, off, unc) in enumerate(base)
    ]


def block(node: str, run: str, stages: list[str], kinds: dict[str, str], has_exit: np.ndarray, frames: list[dict],
          clock: str, cursor: int, **paging) -> dict:
    """A page of frames; ``cursor`` is where the next page starts, ``paging`` the figures of its
    kind of source (live: ``newest``, ``correction_ns``; stored: ``total``); ``kinds``: stage
    name -> element factory."""
    return {"node": node, "run": run, "stages": stages, "kinds": kinds or {},
            "has_exit": [bool(h) for h in has_exit], "clock": clock, "cursor": cursor, **paging, "frames": frames}


def _ms_values(ns: np.ndarray) -> list[float | None]:
    return [None if v != v else v for v in (ns / NS_PER_MS).tolist()]


def _ms_lists(ns: np.ndarray) -> list[list[float | None]]:
    return [[None if v != v else v for v in row] for row in (ns / NS_PER_MS).tolist()]


def _lists(values: np.ndarray) -> list[list[int | None]]:
    return [[None if v == MISSING else v for v in row] for row in values.tolist()]
