"""``dcuscope serve-rtsp``: live RTSP streams on loopback from video files, like IP cameras.

Each clip is decoded, looped forever, re-encoded as H.264 (x264, zero-latency) and served at
``rtsp://HOST:PORT/camN`` in real time, so that pipelines can compare "video stream data"
(live) with "video file data" as in the paper.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

from dcuscope.core import signals
from dcuscope.core.errors import ConfigError, PipelineError, UsageError
from dcuscope.core.gst import GLib, Gst, rtsp_server
from dcuscope.core.ports import check_port_free
from dcuscope.pipeline.config import SourceConfig
from dcuscope.pipeline.sources import SourceBin
from dcuscope import plugins

GstRtspServer = rtsp_server()  # serve-rtsp imports this module: it names the package if missing

DEFAULT_PORT = 8554
DEFAULT_BITRATE = 2000  # kbit/s


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class LoopingClipFactory(GstRtspServer.RTSPMediaFactory):
    """Serves one clip, shared by all clients, looping, paced at its own frame rate."""

    def __init__(self, clip: Path, index: int, bitrate: int, keyframe_every: int, say: Callable[[str], None] = _stderr):
        super().__init__()
        self.clip, self.index, self.bitrate, self.keyframe_every = clip, index, bitrate, keyframe_every
        self.say = say
        self.set_shared(True)
        self.connect("media-configure", self._on_media_configure)

    def _on_media_configure(self, _factory, media: GstRtspServer.RTSPMedia) -> None:
        # The media watches its pipeline's bus itself and keeps what goes wrong to GStreamer's debug
        # log: a clip that cannot loop would end its stream without a word here. A sync handler sees
        # the messages too (once each, in the thread that posts them).
        bus = media.get_element().get_parent().get_bus()
        bus.enable_sync_message_emission()
        bus.connect("sync-message::warning", self._on_trouble)
        bus.connect("sync-message::error", self._on_trouble)

    def _on_trouble(self, _bus, message: Gst.Message) -> None:
        warning = message.type == Gst.MessageType.WARNING
        err, _debug = message.parse_warning() if warning else message.parse_error()
        self.say(f"{'warning' if warning else 'error'}: cam{self.index} ({self.clip}): {err.message}")

    def do_create_element(self, _url):
        media = Gst.Bin.new(f"cam{self.index}")
        source = SourceBin(SourceConfig(kind="uri", location=self.clip.as_uri(), loop=True), self.index, 0)
        chain = [Gst.ElementFactory.make(f) for f in ("videoconvert", "x264enc", "rtph264pay")]
        if any(e is None for e in chain):
            raise PipelineError("x264enc or rtph264pay missing: is the setup complete? (make setup)")
        convert, encoder, payloader = chain
        Gst.util_set_object_arg(encoder, "tune", "zerolatency")
        Gst.util_set_object_arg(encoder, "speed-preset", "ultrafast")
        encoder.set_property("bitrate", self.bitrate)
        encoder.set_property("key-int-max", self.keyframe_every)
        payloader.set_property("name", "pay0")
        payloader.set_property("pt", 96)
        media.add(source)
        for element in chain:
            media.add(element)
        source.link(convert)
        convert.link(encoder)
        encoder.link(payloader)
        return media


def keyframe_interval(clip: Path) -> int:
    """Frames between key frames: one a second at the clip's own rate, as IP cameras do
    (a client joining mid-stream waits at most a second for its first picture)."""
    from gi.repository import GstPbutils

    try:
        info = GstPbutils.Discoverer.new(10 * Gst.SECOND).discover_uri(clip.resolve().as_uri())
    except GLib.Error as exc:
        raise PipelineError(f"{clip}: cannot read it as video: {exc.message}") from exc
    streams = info.get_video_streams()
    if not streams:
        raise PipelineError(f"{clip}: no video stream in it")
    num, den = streams[0].get_framerate_num(), streams[0].get_framerate_denom()
    return max(1, round(num / den)) if num > 0 and den > 0 else 30


def serve(clips: list[Path], host: str = "127.0.0.1", port: int = DEFAULT_PORT, bitrate: int = DEFAULT_BITRATE,
          announce=print) -> None:
    """Serve ``clips`` at rtsp://host:port/cam0, /cam1, ... until Ctrl-C."""
    plugins.register()
    for clip in clips:
        if not clip.is_file():
            raise ConfigError(f"{clip}: no such video file")
    check_port_free(host, port)
    server = GstRtspServer.RTSPServer()
    server.set_address(host)
    server.set_service(str(port))
    mounts = server.get_mount_points()
    for index, clip in enumerate(clips):
        gop = keyframe_interval(clip)
        mounts.add_factory(f"/cam{index}", LoopingClipFactory(clip.resolve(), index, bitrate, gop))
    if server.attach(None) == 0:
        raise UsageError(f"--port {port}: cannot listen on {host}:{port}: pick a free one with --port")
    for index, clip in enumerate(clips):
        announce(f"rtsp://{host}:{port}/cam{index}  <-  {clip}")
    loop = GLib.MainLoop()
    for signum in (2, 15):  # SIGINT, SIGTERM
        GLib.unix_signal_add(GLib.PRIORITY_HIGH, signum, lambda: loop.quit() or False)
    if signals.held() is None:  # else Ctrl-C came while starting up
        loop.run()
