"""The clocks probes can read, by name: Linux clock ids for ``time.clock_gettime_ns``.

``realtime`` is what PTP's phc2sys disciplines, so it is the default everywhere.

:class:`PretendClock` is the testing aid ``--clock-offset-ms`` / ``--clock-drift-ppm``: a node
pretends its clock is off (and runs fast or slow), so that the relay must notice.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

CLOCKS = {"realtime": 0, "monotonic": 1, "tai": 11}

NEVER = float("-inf")
"""The ``time.monotonic()`` of something that has not happened yet (a last pass, a last report).
Never 0.0: the monotonic clock counts from boot, so on a machine up for less than an interval
``now - 0.0 >= interval`` is false, and a first pass that should be due at once is not."""


@dataclass(frozen=True)
class PretendClock:
    """pretend(real) = real + offset_ns + drift_ppm * 1e-6 * (real - start_ns).

    ``real`` is a reading of the probes' clock; ``start_ns`` a reading of it when the run started,
    so that the drift grows from 0 there. Events, WebSocket and UDP clock exchanges of one node all
    go through the same instance: the relay sees one consistent (wrong) clock.
    """
    offset_ns: int = 0
    drift_ppm: float = 0.0
    clock_id: int = CLOCKS["realtime"]
    start_ns: int = field(default=-1)

    def __post_init__(self) -> None:
        if self.start_ns < 0:
            object.__setattr__(self, "start_ns", time.clock_gettime_ns(self.clock_id))

    @property
    def shifts(self) -> bool:
        return bool(self.offset_ns) or bool(self.drift_ppm)

    def of(self, real_ns: int) -> int:
        """The pretend time of one real reading."""
        return real_ns + self.offset_ns + round(self.drift_ppm * 1e-6 * (real_ns - self.start_ns))

    def shift(self, real_ns: np.ndarray) -> np.ndarray:
        """The pretend times of an int64 array of real readings."""
        ts = np.asarray(real_ns, dtype=np.int64)
        drift = np.rint(self.drift_ppm * 1e-6 * (ts - self.start_ns).astype(np.float64)).astype(np.int64)
        return ts + self.offset_ns + drift

    def now(self) -> int:
        return self.of(time.clock_gettime_ns(self.clock_id))
