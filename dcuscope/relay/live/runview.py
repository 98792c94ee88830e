"""What the HTTP API reads of a run, whether this relay holds it or mirrors it from a shared store.

A run this relay holds is read from its live state (:class:`dcuscope.relay.live.state.RunState`); a run
another relay holds, from a mirror of its stored batches (:mod:`dcuscope.relay.live.mirror`). Both give a
:class:`RunView`, and the frames and statistics answered are shaped alike.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from dcuscope.protocol.events import TraceHeader
from dcuscope.relay.clock.correction import Correction
from dcuscope.relay.live import framepack
from dcuscope.relay.live.framejson import block, frame_dicts
from dcuscope.relay.live.run import LiveRun


@dataclass
class RunView:
    node: str
    run: str
    session: int
    header: TraceHeader
    live: LiveRun
    correction: Correction
    stats: Callable[[bool], dict]
    """The run's statistics (``fresh``: recomputed now), shaped as ``GET /api/stats``."""
    relay: str
    """The name of the relay holding the run."""


KNOWN_CLOCK = ("estimate", "ptp")
"""Corrections that say where the node's clock stands against the relay's."""


def window_end_ns(live: LiveRun, correction: Correction) -> int:
    """Where ``live``'s rolling window ends now (:meth:`LiveRun.present_ns`): bounded by the relay's
    clock moved to the node's where the run's correction is known, so that a run read back from the
    store (a mirror, a relay restarted) is not taken for one heard from just now."""
    present = live.present_ns()  # merges what came: live.newest is the newest event now
    if correction.applied not in KNOWN_CLOCK:
        return present
    return live.present_ns(time.time_ns() + correction.at(live.newest)[0])


def frames_block(view: RunView, since: int = 0, limit: int = 200, newest: bool = False) -> dict:
    """Complete frames after cursor ``since``, clock-corrected, as the UI draws them: the first
    ``limit`` of them (paging), or with ``newest`` the last ``limit`` (pushes)."""
    live, correction = view.live, view.correction
    n, fd = live.recent(since, limit, newest)
    frames = frame_dicts(n, fd, correction)
    end = int(fd.chains.end[-1]) if len(fd.chains.end) else None
    return _block(view, end, frames, cursor=frames[-1]["n"] if frames else since)


def columns_block(view: RunView, since: int = 0, limit: int = 200) -> tuple[dict, tuple]:
    """The last ``limit`` complete frames after cursor ``since``, as the pushes carry them: the block
    without its frames, and their columns as the run kept them when it showed them, moved to the
    relay's clock (:func:`dcuscope.relay.live.framepack.corrected`; the pusher packs them once per size
    asked, :func:`dcuscope.relay.live.framepack.packed`)."""
    ints, floats = view.live.recent_columns(since, limit)
    stages = len(view.header.stages)
    end = int(ints[4, -1]) if ints.shape[1] else None  # INT_FIELDS: n, source, frame, origin, end
    cursor = int(ints[0, -1]) if ints.shape[1] else since
    return _block(view, end, [], cursor), framepack.corrected(ints, floats, view.correction, stages)


def _block(view: RunView, end: int | None, frames: list[dict], cursor: int) -> dict:
    """``end``: the last frame's end on the node's clock, where its correction is looked up (None: now)."""
    corr, bound = view.correction.at(end if end is not None else time.time_ns())
    return block(view.node, view.run, view.header.stages, view.header.kinds, view.live.has_exit, frames,
                 view.correction.applied, cursor=cursor, newest=view.live.visible, correction_ns=corr,
                 uncertainty_ns=bound)
