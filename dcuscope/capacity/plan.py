"""The configuration of one stream count: the user's pipeline with its sources replicated.

Stream i plays the config's source i modulo their number (sources are cycled); the mux's
batch size is the stream count unless ``keep_batch``; a tiler whose grid holds fewer tiles than
streams gets the smallest grid that holds them all (as square as possible, wider than tall).
File sources play in real time, as cameras would (``live``, looped); with RTSP they are served as
live streams instead (:mod:`.rtspserve`), and the mux is told its sources are live.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from fractions import Fraction
from types import MappingProxyType

from dcuscope.core.errors import UsageError
from dcuscope.pipeline.config import PipelineConfig, SourceConfig, StageConfig

RTSP_LATENCY_MS = 200
"""rtspsrc's jitter buffer for served streams (its default 2000 ms adds 2 s to every frame)."""


@dataclass(frozen=True)
class Adjusted:
    """What a stream count changed in the config besides its sources, said once in the report."""

    batch_size: bool
    tiler_grid: bool


def check_replicable(config: PipelineConfig, rtsp: bool) -> None:
    """UsageError (one line) when ``config`` cannot be run at other stream counts."""
    if config.launch is not None:
        raise UsageError(f"{config.file}: a launch: pipeline has no sources to replicate: capacity needs sources: "
                         "and stages: (the structured form)")
    if not config.stages or config.stages[0].factory != "mux":
        raise UsageError(f"{config.file}: the first stage is not a mux: streams cannot be batched (add '- mux: {{}}' "
                         "first)")
    for index, source in enumerate(config.sources):
        what = f"{config.file}: source {index} ({source.description})"
        if source.kind == "camera":
            raise UsageError(f"{what} cannot be replicated: a V4L2 device is read by one pipeline at a time (use "
                             "a recording of it as a file source)")
        if source.location.startswith("udp://"):
            raise UsageError(f"{what} cannot be replicated: a UDP port is bound by one reader (use a recording of "
                             "it as a file source, or serve it over RTSP)")
        if rtsp and not source.location.startswith("file://"):
            raise UsageError(f"{what}: --rtsp serves file sources as RTSP streams; this one is not a file")


def source_rate(config: PipelineConfig) -> Fraction | None:
    """The rate every source is forced to, when they all say the same one (else None: read from the run)."""
    rates = {s.rate for s in config.sources}
    return rates.pop() if len(rates) == 1 else None


def grid(streams: int) -> tuple[int, int]:
    """(rows, columns) of a collage of ``streams`` tiles: as square as possible, wider than tall."""
    columns = math.ceil(math.sqrt(streams))
    return math.ceil(streams / columns), columns


def for_streams(config: PipelineConfig, streams: int, keep_batch: bool = False,
                rtsp_uris: list[str] | None = None, rtsp_mux_timeout_us: int | None = None) -> PipelineConfig:
    """``config`` at ``streams`` streams (module docstring); ``rtsp_uris``: stream i's served URI."""
    sources = []
    for i in range(streams):
        base = config.sources[i % len(config.sources)]
        if rtsp_uris is not None:
            sources.append(SourceConfig(kind="uri", location=rtsp_uris[i], stall_timeout=base.stall_timeout,
                                        latency_ms=RTSP_LATENCY_MS, rate=base.rate, width=base.width,
                                        height=base.height))
        elif base.location.startswith("file://") or base.kind == "test":
            sources.append(replace(base, live=True, loop=base.kind == "uri" or base.loop))
        else:
            sources.append(base)
    stages = [_adjust(stage, streams, keep_batch, rtsp_uris is not None, rtsp_mux_timeout_us)
              for stage in config.stages]
    return replace(config, sources=tuple(sources), stages=tuple(stages))


def adjusted(config: PipelineConfig, streams: int, keep_batch: bool) -> Adjusted:
    """What :func:`for_streams` changes at ``streams`` besides the sources."""
    tilers = [s for s in config.stages if s.factory == "tiler"]
    return Adjusted(batch_size=not keep_batch, tiler_grid=any(_grid_too_small(t, streams) for t in tilers))


def _grid_too_small(stage: StageConfig, streams: int) -> bool:
    rows, columns = stage.properties.get("rows"), stage.properties.get("columns")
    return rows is not None and columns is not None and int(rows) * int(columns) < streams


def _adjust(stage: StageConfig, streams: int, keep_batch: bool, live: bool, timeout_us: int | None) -> StageConfig:
    props = dict(stage.properties)
    if stage.factory == "mux":
        if not keep_batch:
            props["batch-size"] = streams
        if live:
            props["live-source"] = True
            if timeout_us is not None:
                props.setdefault("batched-push-timeout", timeout_us)
    elif stage.factory == "tiler" and _grid_too_small(stage, streams):
        props["rows"], props["columns"] = grid(streams)
    else:
        return stage
    return replace(stage, properties=MappingProxyType(props))
