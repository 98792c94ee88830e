"""``dcuscope serve-rtsp``: live RTSP streams on loopback from video files, like IP cameras.

Each clip is decoded, looped forever, re-encoded as H.264 (x264, zero-latency) and served at
``rtsp://HOST:PORT/camN`` in real time, so that pipelines can compare "video stream data"
(live) with "video file data" as in the paper.
"""

from __future__ import annotations

from pathlib import Path

import plugins
from pipeline.config import SourceConfig
from pipeline.errors import ConfigError, PipelineError
from pipeline.gst import GLib, Gst
from pipeline.sources import SourceBin

from gi.repository import GstRtspServer  # noqa: E402  (version pinned by pipeline.gst)

DEFAULT_PORT = 8554
DEFAULT_BITRATE = 2000  # kbit/s


class LoopingClipFactory(GstRtspServer.RTSPMediaFactory):
    """Serves one clip, shared by all clients, looping, paced at its own frame rate."""

    def __init__(self, clip: Path, index: int, bitrate: int):
        super().__init__()
        self.clip, self.index, self.bitrate = clip, index, bitrate
        self.set_shared(True)

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
        encoder.set_property("key-int-max", 30)
        payloader.set_property("name", "pay0")
        payloader.set_property("pt", 96)
        media.add(source)
        for element in chain:
            media.add(element)
        source.link(convert)
        convert.link(encoder)
        encoder.link(payloader)
        return media


def serve(clips: list[Path], host: str = "127.0.0.1", port: int = DEFAULT_PORT, bitrate: int = DEFAULT_BITRATE,
          announce=print) -> None:
    """Serve ``clips`` at rtsp://host:port/cam0, /cam1, ... until Ctrl-C."""
    plugins.register()
    for clip in clips:
        if not clip.is_file():
            raise ConfigError(f"{clip}: no such video file")
    server = GstRtspServer.RTSPServer()
    server.set_address(host)
    server.set_service(str(port))
    mounts = server.get_mount_points()
    for index, clip in enumerate(clips):
        mounts.add_factory(f"/cam{index}", LoopingClipFactory(clip.resolve(), index, bitrate))
    if server.attach(None) == 0:
        raise PipelineError(f"cannot listen on {host}:{port} (in use?)")
    for index, clip in enumerate(clips):
        announce(f"rtsp://{host}:{port}/cam{index}  <-  {clip}")
    loop = GLib.MainLoop()
    for signum in (2, 15):  # SIGINT, SIGTERM
        GLib.unix_signal_add(GLib.PRIORITY_HIGH, signum, lambda: loop.quit() or False)
    loop.run()
