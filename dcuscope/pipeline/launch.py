"""A ``launch:`` config: any graph in gst-launch syntax, dcuscope's elements available.

    launch: >
      compositor name=mix ! videoconvert ! fakesink
      videotestsrc is-live=true ! video/x-raw,framerate=30/1 ! mix.
      videotestsrc is-live=true pattern=ball ! video/x-raw,framerate=10/1 ! mix.

Its elements carry no framestamp: ``--probes`` traces it with the dcuscope GStreamer tracer,
as any application (probes.capture.processtracer), every element a stage, every branch traced.
"""

from __future__ import annotations

from dcuscope.core.gst import GLib, Gst
from dcuscope.pipeline.build import BuiltPipeline
from dcuscope.pipeline.config import PipelineConfig
from dcuscope.pipeline.elements import check_launch_choices
from dcuscope import plugins


def build_launch(config: PipelineConfig) -> BuiltPipeline:
    """Build (not start) the pipeline of a ``launch:`` config; ConfigError naming the line if
    GStreamer cannot (an unknown element or property, a link that cannot be made)."""
    plugins.register()
    try:
        built = Gst.parse_launch(config.launch)
    except GLib.Error as exc:
        raise config.document.error(("launch",), f"GStreamer cannot build it: {exc.message}") from exc
    if isinstance(built, Gst.Pipeline):
        pipeline = built
    else:  # one element alone
        pipeline = Gst.Pipeline.new(config.node)
        pipeline.add(built)
    pipeline.set_name(config.node)
    check_launch_choices(config.document, ("launch",), pipeline)
    sinks = [e for e in pipeline.iterate_recurse() if e.get_factory() is not None
             and e.flags & Gst.ElementFlags.SINK]
    if not sinks:
        raise config.document.error(("launch",), "the pipeline has no sink element (end it with fakesink, "
                                                 "autovideosink, filesink ...)")
    # Newest first in a bin: the first sink written in the line is the last found.
    return BuiltPipeline(pipeline, sources=[], stages=[], sink=sinks[-1], scaled_to=[])
