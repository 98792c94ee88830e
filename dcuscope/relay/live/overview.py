"""One compact row per DCU, for the fleet overview (``overview`` pushes, ``GET /api/overview``).

A row holds what tells which DCU needs a look: its state (:func:`connection_state`) and, from the
run's rolling window (the figures the stage view's "window" shows), frames per second over all
sources (None once the run ended: it has no rate, and says "ended"; a run gone silent reads 0
within the window's 10 s, :meth:`dcuscope.relay.live.run.LiveRun.present_ns`), the frame delay p99, the
bottleneck and its utilization (of a run that ended, its whole run's, ``figures`` saying which), the clock's state, drops, and alerts: short texts for what the shipped Prometheus alert rules (configs/prometheus/dcuscope-rules.yml)
would fire on, judged here from the relay's own figures so that a page without Prometheus shows
them too.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

CLOCK_UNCERTAIN_US = 1000.0
"""As the rules' DcuscopeClockUncertaintyHigh: a clock bound above 1 ms."""
DROPS_WINDOW_S = 60.0
"""Frames dropped or lost within this long are an alert."""
CONFLICT_WINDOW_S = 60.0


def connection_state(connected: bool, ended: bool) -> str:
    """A DCU's state in a word, as rows and node views carry it beside ``connected`` and ``ended``, so
    that a client need not derive it (and a fleet can say "relay silent", :mod:`dcuscope.relay.api.fleet`)."""
    return "connected" if connected else "ended" if ended else "disconnected"


@dataclass
class CountHistory:
    """A run's count of something (drops, incomplete frames) over the last DROPS_WINDOW_S: (monotonic time, count)."""

    samples: deque = field(default_factory=deque)

    def recent(self, count: int, now: float) -> int:
        """The increase within the window, noting ``count`` as the count now."""
        self.samples.append((now, count))
        while len(self.samples) > 1 and self.samples[1][0] <= now - DROPS_WINDOW_S:
            self.samples.popleft()
        return count - self.samples[0][1]


def overview_row(view: dict, window: dict, relay: str, limit_ns: int | None, drops_recent: int,
                 incomplete_recent: int, whole: dict | None = None) -> dict:
    """The row of one DCU: ``view`` as ``RelayState.node_view``, ``window`` its rolling-window
    statistics, ``relay`` the name of the relay holding it, ``limit_ns`` its frame delay limit
    (``--frame-limit``, None without one), ``drops_recent`` frames dropped or lost and
    ``incomplete_recent`` frames given up incomplete (evicted) within DROPS_WINDOW_S.

    A run that ended has no window to speak of (it empties as its frames age out, its p99 drifting
    to nothing): its row gives ``whole``, the run's whole-run statistics, instead, and says so in
    ``figures`` ("whole run"; "window" otherwise)."""
    fps_by_source = window.get("fps") or {}
    fps = float(sum(fps_by_source.values())) if fps_by_source and not view["ended"] else None
    at_end = view["ended"] and whole is not None
    figures = whole if at_end else window
    p99 = (figures.get("frame") or {}).get("p99_ms")
    neck = figures.get("bottleneck")
    bottleneck = ({"stage": neck["stage"], "utilization": neck.get("utilization"), "saturated": neck.get("saturated")}
                  if neck else None)
    alerts = _alerts(view, bottleneck, p99, limit_ns, drops_recent, incomplete_recent)
    return {"node": view["node"], "run": view["run"], "relay": relay, "connected": view["connected"],
            "ended": view["ended"], "state": connection_state(view["connected"], view["ended"]), "fps": fps,
            "p99_ms": p99, "figures": "whole run" if at_end else "window", "frames": view["frames"]["shown"],
            "drops": view["drops"], "bottleneck": bottleneck,
            "clock": view["clock"], "ptp": view["ptp"], "alerts": alerts, "updated_ns": time.time_ns()}


def _alerts(view: dict, bottleneck: dict | None, p99: float | None, limit_ns: int | None, drops_recent: int,
            incomplete_recent: int) -> list[str]:
    out = []
    if not view["connected"] and not view["ended"]:
        out.append("disconnected")
    if limit_ns is not None and p99 is not None and p99 * 1e6 > limit_ns:
        out.append(f"frame p99 {p99:.1f} ms over its limit {limit_ns / 1e6:g} ms")
    if bottleneck is not None and bottleneck.get("saturated"):
        util = bottleneck.get("utilization")
        out.append(f"stage {bottleneck['stage']} saturated" + (f" ({100 * util:.0f} %)" if util is not None else ""))
    if drops_recent > 0:
        out.append(f"{drops_recent} frames dropped or lost in {DROPS_WINDOW_S:.0f} s")
    if incomplete_recent > 0:  # frames still in flight are not counted: only those given up
        out.append(f"{incomplete_recent} frames left incomplete in {DROPS_WINDOW_S:.0f} s")
    uncertainty = view["clock"].get("uncertainty_us")
    if uncertainty is not None and uncertainty > CLOCK_UNCERTAIN_US:
        out.append(f"clock uncertain (±{uncertainty:.0f} µs)")
    if (view.get("ptp") or {}).get("state") == "lost":
        out.append("PTP lost")
    if view.get("conflict_at") and time.time() - view["conflict_at"] < CONFLICT_WINDOW_S:
        out.append("another run claimed its name")
    return out
