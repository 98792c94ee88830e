"""The gauges and counters of ``/metrics`` per node, read from ``RelayState`` at scrape time.

Every figure is one the relay already derives: the rolling window's statistics (what
``/api/stats`` gives as ``window``: utilization, bottleneck, fps per source, the run's drop and
loss counts per source), the clock view (``/api/nodes`` clock), the node's PTP report and its
counters. The window is the one the UI's pushes use (``RunState.window``: it ends at the present, so
the fps of a run that went silent falls to 0 within ``window_s``; that of a run that ended is 0 at
once. Recomputed at most every ``relay.live.state.WINDOW_MAX_AGE_S``, less often when windows are
costly, and no more once it holds nothing until new events come), so that scrapes of many nodes
cost little. Every source lists every drop reason a node may send
(``protocol.events.DROP_REASONS``, a closed set the wire checks), at 0 before its first drop, so that
``increase()`` sees that drop too; sources per node are bounded by ``--limit sources``.

Only the runs this relay holds (``RelayState.holds``) have their figures here. On a shared store a
run kept in memory whose connection ended (kept to be shown, while another relay may take it) has
only the :data:`STATE` series: connected 0, ended, last seen and its run. They say what this relay
last saw of the node, so that the rules tell a node that stopped or was lost from one that moved to
another relay (whose series are newer: see configs/prometheus/README.md); counts, histograms and
window figures come from the one relay that holds the run, never from two.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from dcuscope.protocol.events import DROP_REASONS
from dcuscope.protocol.wire import PTP_STATES
from dcuscope.relay.live.state import RelayState, RunState, spool_view

MAX_URI_CHARS = 200
NS_PER_S = 1e9
REASONS = sorted(set(DROP_REASONS.values()))

SPECS = {
    "dcuscope_stage_utilization": ("gauge", "Busy fraction of the stage over the rolling window", ("stage",)),
    "dcuscope_stage_saturated": ("gauge", "1 if the stage is the window's bottleneck and saturated", ("stage",)),
    "dcuscope_bottleneck": ("gauge", "1 for the stage /api/stats names as the window's bottleneck", ("stage",)),
    "dcuscope_source_fps": ("gauge", "Complete frames per second of the source over the rolling window", ("source",)),
    "dcuscope_source_nominal_fps": ("gauge", "The source's nominal frame rate", ("source",)),
    "dcuscope_source_info": ("gauge", "The source's URI", ("source", "uri")),
    "dcuscope_source_frames_delivered": ("counter", "Frames that reached the source's origin stage", ("source",)),
    "dcuscope_source_frames_lost": ("counter", "Frames lost before the pipeline (upstream) or by its decoder",
                                    ("source", "where")),
    "dcuscope_source_frames_dropped": ("counter", "Frames the pipeline dropped, per reason", ("source", "reason")),
    "dcuscope_frames_complete": ("counter", "Frames finalised complete", ()),
    "dcuscope_frames_incomplete": ("counter", "Frames evicted incomplete", ()),
    "dcuscope_probe_events_dropped": ("counter", "Events the node's probes dropped", ()),
    "dcuscope_probe_batches_lost": ("counter", "Batches the node lost before the relay had them", ()),
    "dcuscope_node_spool_bytes": ("gauge", "Bytes the node keeps on disk until a relay stored them (every run)", ()),
    "dcuscope_node_spool_oldest_age_seconds": ("gauge", "Age of the oldest event in the node's spool", ()),
    "dcuscope_frame_delay_limit_seconds": ("gauge", "The node's --frame-limit", ()),
    "dcuscope_clock_offset_seconds": ("gauge", "Estimated clock offset, node - relay", ()),
    "dcuscope_clock_uncertainty_seconds": ("gauge", "Bound on the error of the correction applied now", ()),
    "dcuscope_clock_correction_seconds": ("gauge", "Correction subtracted from the node's timestamps now", ()),
    "dcuscope_ptp_state": ("gauge", "1 for the node's PTP state, 0 for the others", ("state",)),
    "dcuscope_ptp_master_offset_seconds": ("gauge", "PTP offset from the master, as ptp4l reports it", ()),
    "dcuscope_node_connected": ("gauge", "1 while the node's newest run is connected to this relay", ()),
    "dcuscope_node_ended": ("gauge", "1 once the node's newest run said it ended (a clean stop, not a loss)", ()),
    "dcuscope_node_last_seen_timestamp_seconds": ("gauge", "When the relay last heard from the node", ()),
    "dcuscope_node_info": ("gauge", "The node's newest run and its session", ("run", "session")),
    "dcuscope_relay_ingest_lag_seconds": ("gauge", "Relay's now - the node's newest event (clock-corrected)", ()),
}
"""Name -> (type, help, labels besides ``node``); counters without their ``_total`` suffix."""
STATE = ("dcuscope_node_connected", "dcuscope_node_ended", "dcuscope_node_last_seen_timestamp_seconds",
         "dcuscope_node_info")
"""The only series of a run kept in memory but not held (see the module docstring)."""


class Families:
    """One metric family per :data:`SPECS` entry, made up front so that each scrape lists them all."""

    def __init__(self) -> None:
        self._f: dict[str, Metric] = {}
        for name, (kind, doc, labels) in SPECS.items():
            cls = GaugeMetricFamily if kind == "gauge" else CounterMetricFamily
            self._f[name] = cls(name, doc, labels=["node", *labels])

    def add(self, name: str, labels: list[str], value: float) -> None:
        self._f[name].add_metric(labels, value)

    def __iter__(self) -> Iterator[Metric]:
        return iter(self._f.values())


class NodeMetrics:
    """The gauge and counter families of every node's newest run."""

    def __init__(self, state: RelayState) -> None:
        self._state = state

    def families(self) -> Iterator[Metric]:
        out = Families()
        runs = [self._state.runs[run] for _, run in sorted(self._state.nodes.items()) if run in self._state.runs]
        for rs in runs:
            _state_samples(out, rs)
            if not self._state.holds(rs):
                continue  # kept to be shown, another relay's to take: its state only
            window = self._state.window(rs, fresh=False)
            _window_samples(out, rs.node, window)
            # The counters now (cheap), the fps as of the window: 0 once the run ended (it has no rate).
            fps = {} if rs.ended else window["fps"]
            _source_samples(out, rs, rs.live.accounting.sources(fps), self._state.limits.sources)
            _node_samples(out, self._state, rs)
        return iter(out)


def _window_samples(out: Families, node: str, window: dict) -> None:
    neck = window.get("bottleneck") or {}
    for stage, st in window["stages"].items():
        if st.get("utilization") is not None:
            out.add("dcuscope_stage_utilization", [node, stage], st["utilization"])
        named = neck.get("stage") == stage
        out.add("dcuscope_bottleneck", [node, stage], 1.0 if named else 0.0)
        out.add("dcuscope_stage_saturated", [node, stage], 1.0 if named and neck.get("saturated") else 0.0)


def _source_samples(out: Families, rs: RunState, sources: dict[str, dict], max_sources: int) -> None:
    node = rs.node
    sources = dict(list(sources.items())[:max_sources])
    for sid, src in sources.items():
        uri = rs.header.sources.get(int(sid))
        if uri is not None:
            out.add("dcuscope_source_info", [node, sid, str(uri)[:MAX_URI_CHARS]], 1.0)
        out.add("dcuscope_source_fps", [node, sid], src["fps"])
        if src["nominal_fps"] is not None:
            out.add("dcuscope_source_nominal_fps", [node, sid], src["nominal_fps"])
        out.add("dcuscope_source_frames_delivered", [node, sid], src["delivered"])
        out.add("dcuscope_source_frames_lost", [node, sid, "upstream"], src["lost_upstream"])
        out.add("dcuscope_source_frames_lost", [node, sid, "decoder"], src["decoder_dropped"])
        for reason in REASONS:
            out.add("dcuscope_source_frames_dropped", [node, sid, reason], src["dropped"].get(reason, 0))


def _state_samples(out: Families, rs: RunState) -> None:
    """What this relay last saw of the node's newest run (:data:`STATE`), held or not."""
    node = rs.node
    out.add("dcuscope_node_connected", [node], 1.0 if rs.sid is not None else 0.0)
    out.add("dcuscope_node_ended", [node], 1.0 if rs.ended else 0.0)
    out.add("dcuscope_node_last_seen_timestamp_seconds", [node], rs.last_seen)
    out.add("dcuscope_node_info", [node, rs.run, str(rs.session)], 1.0)


def _node_samples(out: Families, state: RelayState, rs: RunState) -> None:
    node, live = rs.node, rs.live
    out.add("dcuscope_frames_complete", [node], live.finalised)
    out.add("dcuscope_frames_incomplete", [node], live.evicted)
    out.add("dcuscope_probe_events_dropped", [node], rs.dropped)
    out.add("dcuscope_probe_batches_lost", [node], rs.lost)
    spool = spool_view(rs.spool)
    if spool["spool_bytes"] is not None:
        out.add("dcuscope_node_spool_bytes", [node], spool["spool_bytes"])
    if spool["spool_oldest_age_s"] is not None:
        out.add("dcuscope_node_spool_oldest_age_seconds", [node], spool["spool_oldest_age_s"])
    limit = state.frame_limits.limit_ns(node)
    if limit is not None:
        out.add("dcuscope_frame_delay_limit_seconds", [node], limit / NS_PER_S)
    clock = state.clock_view(rs)
    if clock["offset_ns"] is not None:
        out.add("dcuscope_clock_offset_seconds", [node], clock["offset_ns"] / NS_PER_S)
    out.add("dcuscope_clock_uncertainty_seconds", [node], clock["correction_uncertainty_ns"] / NS_PER_S)
    out.add("dcuscope_clock_correction_seconds", [node], clock["correction_ns"] / NS_PER_S)
    ptp = rs.ptp if isinstance(rs.ptp, dict) else {}
    for s in PTP_STATES:  # every state a node may report (protocol.wire sanitises the rest away)
        out.add("dcuscope_ptp_state", [node, s], 1.0 if ptp.get("state") == s else 0.0)
    offset = ptp.get("master_offset_ns")
    if isinstance(offset, int) and not isinstance(offset, bool):
        out.add("dcuscope_ptp_master_offset_seconds", [node], offset / NS_PER_S)
    if live.newest:
        offset_ns, _ = state.correction(rs).at(live.newest)
        out.add("dcuscope_relay_ingest_lag_seconds", [node], (time.time_ns() - (live.newest - offset_ns)) / NS_PER_S)
