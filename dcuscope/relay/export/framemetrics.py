"""The per-frame histograms of ``/metrics``, fed by every finalised batch of frames.

:class:`FrameMetrics` is one of ``RelayState.observers``: told of each run's finalised frames
(``LiveRun.on_finalise``, complete frames, each once), it counts their delay-model figures into
per-node histograms (:class:`dcuscope.relay.export.buckets.Histograms`), so it derives nothing again. Only a
node's newest run is counted: its histograms start empty when the node's newest run changes
(Prometheus reads that as a counter reset) and go when the node leaves ``state.nodes``
(bounded by ``--limit runs_held``). Only the runs the relay holds (``RelayState.holds``) are counted
and shown: on a shared store, a run whose connection ended is another relay's to count. Gap series
(``A->B``) are kept for the first :data:`MAX_GAPS` pairs a run shows; further pairs count together
under ``from_stage="other"``.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
from prometheus_client.core import CounterMetricFamily, Metric
from prometheus_client.utils import floatToGoString

from dcuscope.model.delays import FrameDelays, Series
from dcuscope.relay.export.buckets import Histograms
from dcuscope.relay.export.exposition import BulkHistogram
from dcuscope.relay.live.state import RelayState, RunState

MAX_GAPS = 128
"""Gap pairs per node with series of their own (a pipeline of S stages shows about S)."""
OTHER = "other"
NS_PER_S = 1e9

HISTOGRAMS = {
    "frame": ("dcuscope_frame_delay_seconds", "End-to-end frame delay (origin to end of chain), finalised frames", ()),
    "glass": ("dcuscope_frame_glass_seconds", "Glass-to-glass delay (capture to end of chain, clock-corrected)", ()),
    "stage": ("dcuscope_stage_delay_seconds", "Stage delay (enter to exit)", ("stage",)),
    "service": ("dcuscope_stage_service_seconds", "Stage service time (work on the frame)", ("stage",)),
    "wait": ("dcuscope_stage_wait_seconds", "Stage wait time (queued inside the stage before its work)", ("stage",)),
    "gap": ("dcuscope_gap_seconds", "Gap between a stage's exit and the next stage's enter",
            ("from_stage", "to_stage")),
}
"""Key of a series' family -> (metric name, help, labels besides ``node``)."""


@dataclass
class _NodeFrames:
    run: str
    hist: Histograms
    busy_ns: dict[str, int] = field(default_factory=dict)
    gaps: dict[str, tuple[str, str]] = field(default_factory=dict)
    """Gap name -> its (from_stage, to_stage) labels, for the first MAX_GAPS pairs."""


class FrameMetrics:
    """Histograms of every node's newest run (see the module docstring); ``bounds_s``: the bucket
    upper bounds in seconds."""

    def __init__(self, state: RelayState, bounds_s: Iterable[float]) -> None:
        self._state = state
        bounds_s = list(bounds_s)
        # Compared in whole ns, the unit of the values: a value on a bound lands in its bucket exactly.
        self._bounds_ns = [round(b * NS_PER_S) for b in bounds_s]
        self._le = [floatToGoString(b) for b in bounds_s] + ["+Inf"]
        self._nodes: dict[str, _NodeFrames] = {}

    def observe(self, rs: RunState, fd: FrameDelays, values: Series) -> None:
        """A ``RelayState`` observer: count a finalised batch of ``rs``'s frames."""
        if not self._state.holds(rs):
            return  # another relay may own it now: the frames are its to count
        nf = self._current(rs.node)
        if nf is None or nf.run != rs.run:
            return  # an older run of the node, still finalising: not its newest
        nf.hist.add(self._batch(rs, nf, fd, values))
        for stage, ns in values.busy.items():
            nf.busy_ns[stage] = nf.busy_ns.get(stage, 0) + ns

    def _batch(self, rs: RunState, nf: _NodeFrames, fd: FrameDelays, values: Series) -> list:
        # Glass-to-glass by the correction in force at each frame's origin, as the UI's frames
        # (relay.live.framejson): the capture time is the camera's clock, the end the node's.
        has = ~np.isnan(fd.glass)
        glass = fd.glass[has]
        if len(glass):
            glass = glass - self._state.correction(rs).offsets(fd.chains.end[has], fd.table.origin[has])
        batch = [(("frame",), values.frame), (("glass",), glass)]
        for kind in ("stage", "service", "wait"):
            batch += [((kind, name), v) for name, v in getattr(values, "stages" if kind == "stage" else kind).items()]
        for name, v in values.gaps.items():
            if name not in nf.gaps and len(nf.gaps) < MAX_GAPS:
                nf.gaps[name] = gap_stages(name, rs.header.stages)
            batch.append((("gap", *nf.gaps.get(name, (OTHER, OTHER))), v))
        return batch

    def _current(self, node: str) -> _NodeFrames | None:
        """The node's histograms, empty again when its newest run changed; None once it left."""
        run = self._state.nodes.get(node)
        if run is None:
            self._nodes.pop(node, None)
            return None
        nf = self._nodes.get(node)
        if nf is None or nf.run != run:
            nf = self._nodes[node] = _NodeFrames(run, Histograms(self._bounds_ns))
            nf.hist.ensure(("frame",))
            nf.hist.ensure(("glass",))
        return nf

    def families(self) -> Iterator[Metric]:
        """The histogram families and the busy-time counter, of every node known now."""
        for node in list(self._nodes):
            if node not in self._state.nodes:
                del self._nodes[node]
        hists = {key: BulkHistogram(name, doc, ["node", *labels], self._le)
                 for key, (name, doc, labels) in HISTOGRAMS.items()}
        busy = CounterMetricFamily("dcuscope_stage_busy_seconds", "Stage busy time summed (service over its "
                                   "output buffers, a batch once), finalised frames", labels=["node", "stage"])
        for node in sorted(self._state.nodes):
            nf = self._current(node)
            rs = self._state.node_run(node)
            if rs is None or not self._state.holds(rs):
                continue  # not held: kept (counting goes on if the run comes back here), not shown
            for key, cumulative, total_ns in nf.hist.snapshot():
                hists[key[0]].add_series([node, *key[1:]], cumulative, total_ns / NS_PER_S)
            for stage, ns in nf.busy_ns.items():
                busy.add_metric([node, stage], ns / NS_PER_S)
        yield from hists.values()
        yield busy


def gap_stages(name: str, stages: list[str]) -> tuple[str, str]:
    """The two stages of gap ``name`` ("A->B"), where stage names may hold "->" themselves."""
    known = set(stages)
    at = name.find("->")
    while at >= 0:
        a, b = name[:at], name[at + 2:]
        if a in known and b in known:
            return a, b
        at = name.find("->", at + 1)
    a, _, b = name.partition("->")
    return a, b
