"""Probe events paired by frame identity: one row per (source, frame), one cell per tracepoint.

The input of the delay model (:mod:`dcuscope.model.delays`). Trace files and stored sessions pair all
their events at once (:func:`frame_table`); the relay pairs incrementally into cells and
builds its tables with :func:`frame_table_from_cells`. Where a tracepoint saw a frame twice,
the earliest timestamp is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dcuscope.protocol.errors import ProtocolError
from dcuscope.protocol.events import CAPTURE, ENTER, EXIT, FRAME_CELLS, FRAME_POINTS, GROUP, ORIGIN, READY, TraceHeader

MISSING = -1
"""Timestamp of a tracepoint a frame never hit. Real timestamps (ns) are never negative."""

_NEVER = np.iinfo(np.int64).max


@dataclass
class FrameTable:
    """One row per frame identity (source, frame), sorted by source then frame number."""

    stages: list[str]
    source: np.ndarray
    """(n,) int32."""
    frame: np.ndarray
    """(n,) int64."""
    origin: np.ndarray
    """(n,) int64 ns, MISSING if the origin event is missing."""
    origin_stage: np.ndarray
    """(n,) int64 stage index of the origin event, -1 if missing."""
    enter: np.ndarray
    """(n, n_stages) int64 ns, MISSING where the frame has no enter at that stage."""
    exit: np.ndarray
    """(n, n_stages) int64 ns, MISSING where the frame has no exit at that stage."""
    ready: np.ndarray
    """(n, n_stages) int64 ns: when the stage could start the work that carried the frame out
    (protocol.events, ``ready``), MISSING where unknown (format 1, Python probes)."""
    capture: np.ndarray
    """(n,) int64 ns: the source's capture time of the frame, MISSING where unknown."""
    group: np.ndarray
    """(n, n_stages) int64: the ready event's code, > 0 where the frame was the first of its
    output buffer (whose work then counts once in the stage's busy time), MISSING where unknown."""
    links: list[list[int]] = field(default_factory=list)
    """The graph, ``[a, b]``: stage a feeds stage b (TraceHeader.links); empty: the stages are
    one chain in their order."""

    def __len__(self) -> int:
        return int(self.source.shape[0])


def frame_events(events: np.ndarray) -> np.ndarray:
    """The events that are timestamps of a frame (not drops or facts)."""
    point = events["point"]
    return events if len(point) == 0 or point.max() < FRAME_POINTS else events[point < FRAME_POINTS]


def frame_table(header: TraceHeader, events: np.ndarray) -> FrameTable:
    """Pair the frames' events by identity; where a tracepoint saw a frame twice keep the
    earliest. Drops and facts are not frame timestamps: they are left out here."""
    n_stages = len(header.stages)
    events = frame_events(events)
    stage = events["stage"].astype(np.int64)
    point = events["point"].astype(np.int64)
    if len(events) and (stage.min() < 0 or stage.max() >= n_stages or point.min() < 0):
        raise ProtocolError(f"node {header.node}: event stage or point out of range for {n_stages} stages")
    ts = np.ascontiguousarray(events["ts"], dtype=np.int64)
    row, source, frame = _frame_rows(np.ascontiguousarray(events["source"]), np.ascontiguousarray(events["frame"]))
    n = len(source)

    # Earliest timestamp per (frame, stage, point): a scatter-min, no per-event Python.
    cells = np.full(n * n_stages * FRAME_CELLS, _NEVER, np.int64)
    slot = (row * n_stages + stage) * FRAME_CELLS
    np.minimum.at(cells, slot + point, ts)
    cells[cells == _NEVER] = MISSING
    ready = point == READY
    cells[slot[ready] + GROUP] = events["code"][ready]
    table = frame_table_from_cells(header.stages, source, frame, cells.reshape(n, n_stages, FRAME_CELLS))
    table.links = [list(link) for link in header.links]
    return table


def frame_table_from_cells(stages: list[str], source: np.ndarray, frame: np.ndarray, cells: np.ndarray) -> FrameTable:
    """FrameTable from paired cells: ``cells[row, stage, point]`` = ts or MISSING.

    Cells are 0 origin, 1 enter, 2 exit, 3 ready, 4 capture, 5 group (protocol.events
    FRAME_CELLS; cells of 3 hold the first three only); the relay pairs incrementally and
    builds tables here.
    """
    n = len(source)
    missing = np.full(cells.shape[:2], MISSING, np.int64)
    ready = np.ascontiguousarray(cells[:, :, READY]) if cells.shape[2] > READY else missing
    captures = cells[:, :, CAPTURE] if cells.shape[2] > CAPTURE else missing
    group = np.ascontiguousarray(cells[:, :, GROUP]) if cells.shape[2] > GROUP else missing
    origins = cells[:, :, ORIGIN]
    has_origin = origins != MISSING
    origin_stage = np.where(has_origin.any(axis=1), has_origin.argmax(axis=1), -1)
    origin = np.where(origin_stage >= 0, origins[np.arange(n), np.maximum(origin_stage, 0)], MISSING)
    return FrameTable(
        stages=list(stages), source=np.asarray(source, np.int32), frame=np.asarray(frame, np.int64),
        origin=origin, origin_stage=origin_stage,
        enter=np.ascontiguousarray(cells[:, :, ENTER]), exit=np.ascontiguousarray(cells[:, :, EXIT]),
        ready=ready, group=group, capture=np.where(origin_stage >= 0, captures[np.arange(n), np.maximum(origin_stage, 0)], MISSING),
    )


def _frame_rows(source: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row of each event's frame identity, and the identities sorted by (source, frame)."""
    if len(source) and source.min() >= 0 and source.max() < 1 << 22 and frame.min() >= 0 and frame.max() < 1 << 40:
        # One sort of one int64 key instead of a two-key lexsort: ~3x faster on 1M events.
        keys, row = np.unique((source.astype(np.int64) << 40) | frame, return_inverse=True)
        return row.ravel(), (keys >> 40).astype(np.int32), keys & ((1 << 40) - 1)
    order = np.lexsort((frame, source))
    s_src, s_frame = source[order], frame[order]
    new = np.ones(len(order), bool)
    new[1:] = (s_src[1:] != s_src[:-1]) | (s_frame[1:] != s_frame[:-1])
    row = np.empty(len(order), np.int64)
    row[order] = np.cumsum(new) - 1
    return row, s_src[new].astype(np.int32), s_frame[new].astype(np.int64)
