"""Configuration -> a linked Gst.Pipeline: sources, the chain of stages, the sink."""

from __future__ import annotations

from dataclasses import dataclass, replace

from dcuscope.core.clocks import CLOCKS
from dcuscope.core.errors import ConfigError, PipelineError
from dcuscope.core.gst import Gst
from dcuscope.pipeline.config import PipelineConfig
from dcuscope.pipeline.elements import check_source_and_sink_values, make_stage_element
from dcuscope.pipeline.sinks import Outputs, build_outputs, link_outputs
from dcuscope.pipeline.sources import SourceBin
from dcuscope import plugins


@dataclass
class BuiltPipeline:
    pipeline: Gst.Pipeline
    sources: list[SourceBin]
    stages: list[Gst.Element]
    sink: Gst.Element
    """Where frames leave the stages: the sink bin, or the tee in front of several."""
    scaled_to: list[tuple[int, int] | None]
    """Per source: the size it is scaled to before the mux (the config's, else the mux's), or None."""
    outputs: Outputs | None = None

    def close(self) -> None:
        """Stop what the pipeline serves beside itself (RTSP servers)."""
        if self.outputs is not None:
            self.outputs.close()


def build_pipeline(config: PipelineConfig) -> BuiltPipeline:
    """Build (not start) the pipeline of ``config``. ConfigError for bad stages, PipelineError else."""
    plugins.register()
    check_source_and_sink_values(config)
    pipeline = Gst.Pipeline.new(config.node)
    stages = [make_stage_element(config, stage) for stage in config.stages]
    mux = stages[0] if stages[0].get_factory().get_name() == "mux" else None
    if mux is None and len(config.sources) > 1:
        raise config.document.error(("stages", 0), "with several sources the first stage must be a mux")

    clock_id = CLOCKS[config.probes.clock]
    if mux is not None:
        mux.set_property("clock-id", clock_id)  # its max-latency ages frames on the framestamps' clock
    sources, scaled_to = [], []
    for index, source in enumerate(config.sources):
        if mux is not None and source.width is None and source.height is None:
            # Scale in the source's own streaming thread (native, parallel) so the mux
            # can batch without copying; the result is the same as the mux scaling.
            source = replace(source, width=mux.get_property("width"), height=mux.get_property("height"))
        scaled_to.append((source.width, source.height) if source.width and source.height else None)
        sources.append(SourceBin(source, index, clock_id))
    outputs = build_outputs(config.sinks)
    try:
        return _link(config, pipeline, sources, stages, mux, outputs, scaled_to)
    except Exception:
        outputs.close()
        raise


def _link(config: PipelineConfig, pipeline: Gst.Pipeline, sources: list[SourceBin], stages: list[Gst.Element],
          mux: Gst.Element | None, outputs: Outputs, scaled_to: list) -> BuiltPipeline:
    sink = outputs.head
    for element in [*sources, *stages, *outputs.elements]:
        pipeline.add(element)
    link_outputs(outputs)
    for source in sources:
        target = mux.request_pad_simple("sink_%u") if mux is not None else stages[0].get_static_pad("sink")
        if source.get_static_pad("src").link(target) != Gst.PadLinkReturn.OK:
            raise PipelineError(f"cannot link {source.config.description} to {stages[0].get_name()}")
    for a, b in zip(stages, [*stages[1:], sink]):
        if not a.link(b):
            raise ConfigError(
                f"{config.file}:{config.document.line(('stages',))}: stages: {a.get_name()} cannot be linked to "
                f"{b.get_name()} (their formats do not match: check the order of the stages)"
            )
    return BuiltPipeline(pipeline, sources, stages, sink, scaled_to, outputs)
