"""Sink bins: where the osd's frames go. Each is one stage named ``sink`` (enter point only).

- ``fake``: discard (measure the pipeline alone);
- ``file``: H.264 in the container the file's name says (``videoconvert ! x264enc ! h264parse
  ! mp4mux|matroskamux|avimux ! filesink``), finalised when the run ends with EOS;
- ``frames``: numbered PNG images in a folder (``frame_00000.png`` ...).
"""

from __future__ import annotations

from core.errors import PipelineError
from core.gst import Gst
from pipeline.config import SinkConfig
from pipeline.outputs import CONTAINERS, FRAME_PATTERN


def build_sink(config: SinkConfig) -> Gst.Bin:
    if config.kind == "fake":
        chain = [_make("fakesink", "render", sync=config.sync, async_=False)]
    elif config.kind == "file":
        muxer = CONTAINERS.get(config.path.suffix.lower())
        if muxer is None:
            raise PipelineError(f"{config.path}: unknown video container (expected one of {', '.join(CONTAINERS)})")
        chain = [
            _make("videoconvert", "encconvert"),
            _make("capsfilter", "enccaps", caps=Gst.Caps.from_string("video/x-raw,format=I420")),
            _make("x264enc", "encoder", bitrate=config.bitrate, speed_preset="ultrafast", tune="zerolatency",
                  key_int_max=30),
            _make("h264parse", "parse"),
            _make(muxer, "container"),
            _make("filesink", "render", location=str(config.path), sync=config.sync, async_=False),
        ]
    elif config.kind == "frames":
        config.path.mkdir(exist_ok=True)  # the folder itself; its parent was checked, not made
        chain = [
            _make("videoconvert", "encconvert"),
            _make("pngenc", "encoder", compression_level=1),
            _make("multifilesink", "render", location=str(config.path / FRAME_PATTERN), sync=config.sync,
                  async_=False),
        ]
    else:  # the config parser only lets known kinds through
        raise PipelineError(f"unknown sink type {config.kind}")
    sink = Gst.Bin.new("sink")
    for element in chain:
        sink.add(element)
    for a, b in zip(chain, chain[1:]):
        if not a.link(b):
            raise PipelineError(f"sink: cannot link {a.get_name()} to {b.get_name()}")
    sink.add_pad(Gst.GhostPad.new("sink", chain[0].get_static_pad("sink")))
    return sink


def _make(factory: str, name: str, **props) -> Gst.Element:
    element = Gst.ElementFactory.make(factory, name)
    if element is None:
        raise PipelineError(f"GStreamer element {factory!r} is missing: is the setup complete? (make setup)")
    for key, value in props.items():
        key = key.rstrip("_").replace("_", "-")
        if isinstance(value, str) and not isinstance(element.get_property(key), str):
            Gst.util_set_object_arg(element, key, value)
        else:
            element.set_property(key, value)
    return element
