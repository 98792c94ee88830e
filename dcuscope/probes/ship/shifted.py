"""The --clock-offset-ms and --clock-drift-ppm testing aids on the way out of a node: its events' timestamps
moved through a pretend clock (:class:`dcuscope.core.clocks.PretendClock`)."""

from __future__ import annotations

import numpy as np

from dcuscope.core.clocks import PretendClock
from dcuscope.protocol.events import CAPTURE, Exporter, TraceHeader


class Shifted:
    """Exporter wrapper that moves every timestamp the node's clock took through ``pretend``: the
    --clock-offset-ms and --clock-drift-ppm testing aids, so that a node can pretend its clock is
    off (and runs fast or slow) and the relay must notice; the relay exporter's clock exchanges
    read the same pretend clock. Capture times are left as they are: they are the camera's clock
    (an RTSP sender's reports), which a node whose own clock is off still receives unchanged, and
    which two DCUs of one camera must share for their frames to be matched (relay.api.moments)."""

    def __init__(self, inner: Exporter, pretend: PretendClock):
        self.inner, self.pretend = inner, pretend

    def start(self, header: TraceHeader) -> None:
        header.started_ns = self.pretend.of(header.started_ns)
        self.inner.start(header)

    def write(self, events: np.ndarray) -> None:
        shifted = events.copy()
        own = shifted["point"] != CAPTURE
        shifted["ts"][own] = self.pretend.shift(events["ts"][own])
        self.inner.write(shifted)

    def close(self, dropped: int) -> None:
        self.inner.close(dropped)
