"""Sink bins: where the osd's frames go. Each is one stage (enter point only), named ``sink``
for the one ``sink:`` of a config, else as ``sinks:`` names it.

- ``fake``: discard (measure the pipeline alone);
- ``file``: H.264 in the container the file's name says (``videoconvert ! x264enc ! h264parse
  ! mp4mux|matroskamux|avimux ! filesink``), finalised when the run ends with EOS;
- ``frames``: numbered PNG images in a folder (``frame_00000.png`` ...);
- ``rtsp``: served live as H.264 over RTSP (:mod:`dcuscope.pipeline.rtspout`);
- ``rtp``: H.264 over RTP to ``host:port`` (``videoconvert ! x264enc ! rtph264pay ! udpsink``), for
  another pipeline's ``rtp:`` source;
- ``shm``: raw I420 frames into shared memory (``shmsink``) at ``path``, for another pipeline's
  ``shm:`` source on this machine (which must give the same width, height and rate).

Where the frames go to another pipeline, the dcuscope tracer (--probes) records each one it sends,
so that the relay follows it there (docs/journeys.md).

Several sinks hang off a ``tee`` (named ``tee``), each behind a queue of its own (``NAME_queue``,
leaky: an output more than 30 frames behind drops the oldest there instead of holding the
others; such frames show as incomplete in the trace, they entered the queue and never left).
"""

from __future__ import annotations

from dataclasses import dataclass

from dcuscope.core.errors import PipelineError
from dcuscope.core.gst import Gst
from dcuscope.pipeline.config import SHM_FORMAT, SinkConfig
from dcuscope.pipeline.outputs import CONTAINERS, FRAME_PATTERN
from dcuscope.pipeline.rtspout import RtspOut, h264_encoder, rtsp_chain


SHM_BYTES = 64 << 20
"""A shm sink's shared memory: a few 4K frames, or dozens of 1080p (shmsink's default)."""


@dataclass
class Outputs:
    """What the stages feed: ``head`` (the one sink bin, or the tee), the sink bins, RTSP servers."""

    head: Gst.Element
    elements: list[Gst.Element]
    """Every element to add to the pipeline (head first)."""
    servers: list[RtspOut]

    def close(self) -> None:
        for server in self.servers:
            server.close()


def build_outputs(configs: tuple[SinkConfig, ...]) -> Outputs:
    servers: list[RtspOut] = []
    try:
        bins = [build_sink(c, servers) for c in configs]
    except Exception:
        for server in servers:
            server.close()
        raise
    if len(bins) == 1:
        return Outputs(bins[0], bins, servers)
    tee = _make("tee", "tee")
    elements: list[Gst.Element] = [tee]
    for config, sink in zip(configs, bins):
        # Leaky: a slow branch drops its own frames (the probes count them), the others go on.
        queue = _make("queue", f"{config.name}_queue", leaky="downstream", max_size_buffers=30, max_size_bytes=0,
                      max_size_time=0)
        elements += [queue, sink]
    return Outputs(tee, elements, servers)


def link_outputs(outputs: Outputs) -> None:
    """Link the tee to each branch (after the elements were added to the pipeline)."""
    if len(outputs.elements) == 1:
        return
    tee, rest = outputs.elements[0], outputs.elements[1:]
    for queue, sink in zip(rest[::2], rest[1::2]):
        if not (tee.link(queue) and queue.link(sink)):
            raise PipelineError(f"cannot link the tee to {sink.get_name()}")


def build_sink(config: SinkConfig, servers: list[RtspOut] | None = None) -> Gst.Bin:
    if config.kind == "fake":
        chain = [_make("fakesink", "render", sync=config.sync, async_=False)]
    elif config.kind == "file":
        muxer = CONTAINERS.get(config.path.suffix.lower())
        if muxer is None:
            raise PipelineError(f"{config.path}: unknown video container (expected one of {', '.join(CONTAINERS)})")
        chain = [
            *h264_encoder(_make, config.bitrate),
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
    elif config.kind == "rtsp":
        chain, server = rtsp_chain(config, _make)
        if servers is not None:
            servers.append(server)
    elif config.kind == "rtp":
        chain = [
            *h264_encoder(_make, config.bitrate),
            _make("rtph264pay", "pay", config_interval=-1),
            _make("udpsink", "render", host=config.host, port=config.port, sync=config.sync, async_=False),
        ]
    elif config.kind == "shm":
        chain = [
            _make("videoconvert", "shmconvert"),
            _make("capsfilter", "shmcaps", caps=Gst.Caps.from_string(f"video/x-raw,format={SHM_FORMAT}")),
            _make("shmsink", "render", socket_path=str(config.path), wait_for_connection=False, sync=config.sync,
                  async_=False, shm_size=SHM_BYTES),
        ]
    else:  # the config parser only lets known kinds through
        raise PipelineError(f"unknown sink type {config.kind}")
    sink = Gst.Bin.new(config.name)
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
