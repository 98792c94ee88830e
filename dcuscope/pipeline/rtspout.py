"""The ``rtsp`` sink: the pipeline's frames served live as H.264 over RTSP (GstRtspServer), as
DeepStream apps serve their output, for any RTSP client (VLC, ffplay, another dcuscope).

The sink bin encodes (x264, zero latency, a key frame every second) into an appsink that never
blocks the pipeline (it keeps only the newest access unit when nobody reads). Each client
session of the server's shared media gets the access units through an appsrc, restamped on the
server's clock. The server listens from when the bin is made until :meth:`RtspOut.close`.
"""

from __future__ import annotations

import threading

from dcuscope.core.errors import PipelineError
from dcuscope.core.gst import GLib, Gst, rtsp_server
from dcuscope.pipeline.config import SinkConfig

from gi.repository import GstApp  # noqa: E402  (versions pinned by core.gst)

FEED_LAUNCH = ("( appsrc name=feed is-live=true format=time do-timestamp=true ! h264parse ! "
               "rtph264pay name=pay0 pt=96 config-interval=1 )")


class RtspOut:
    """The server of one ``rtsp`` sink and the appsrc of its shared media, once a client came."""

    def __init__(self, config: SinkConfig):
        self.config = config
        self._feeds: list[GstApp.AppSrc] = []
        self._lock = threading.Lock()
        rtsp = rtsp_server()
        self.server = rtsp.RTSPServer()
        self.server.set_address(config.host)
        self.server.set_service(str(config.port))
        factory = rtsp.RTSPMediaFactory()
        factory.set_launch(FEED_LAUNCH)
        factory.set_shared(True)
        factory.connect("media-configure", self._on_media_configure)
        self.server.get_mount_points().add_factory(config.mount, factory)
        self._source_id = self.server.attach(None)
        if not self._source_id:
            raise PipelineError(f"sink {config.name}: cannot serve {config.url} (port {config.port} in use?)")

    def _on_media_configure(self, _factory, media) -> None:
        feed = media.get_element().get_by_name("feed")
        with self._lock:
            self._feeds.append(feed)
        media.connect("unprepared", lambda *_: self._forget(feed))

    def _forget(self, feed) -> None:
        with self._lock:
            if feed in self._feeds:
                self._feeds.remove(feed)

    def on_sample(self, appsink: GstApp.AppSink) -> Gst.FlowReturn:
        sample = appsink.emit("pull-sample")
        if sample is None:
            return Gst.FlowReturn.EOS
        with self._lock:
            feeds = list(self._feeds)
        if feeds:
            buf = sample.get_buffer().copy()  # shares the memory; times are the server's (do-timestamp)
            buf.pts = buf.dts = Gst.CLOCK_TIME_NONE
            for feed in feeds:
                if feed.get_caps() is None:
                    feed.set_caps(sample.get_caps())
                feed.emit("push-buffer", buf)
        return Gst.FlowReturn.OK

    def close(self) -> None:
        if self._source_id:
            GLib.source_remove(self._source_id)
            self._source_id = 0


def h264_encoder(make, bitrate: int) -> list:
    """videoconvert ! I420 ! x264enc for live output (ultrafast, zero latency, a keyframe every 30
    frames): what the file, rtsp and rtp sinks encode with. ``make(factory, name, **props)``."""
    return [
        make("videoconvert", "encconvert"),
        make("capsfilter", "enccaps", caps=Gst.Caps.from_string("video/x-raw,format=I420")),
        make("x264enc", "encoder", bitrate=bitrate, speed_preset="ultrafast", tune="zerolatency", key_int_max=30),
    ]


def rtsp_chain(config: SinkConfig, make) -> tuple[list[Gst.Element], RtspOut]:
    """The elements of an ``rtsp`` sink bin (``make(factory, name, **props)``) and its server."""
    out = RtspOut(config)
    appsink = make("appsink", "render", sync=config.sync, async_=False, max_buffers=1, drop=True,
                   emit_signals=True)
    appsink.connect("new-sample", out.on_sample)
    chain = [
        *h264_encoder(make, config.bitrate),
        make("h264parse", "parse", config_interval=-1),
        make("capsfilter", "aucaps", caps=Gst.Caps.from_string("video/x-h264,stream-format=byte-stream,alignment=au")),
        appsink,
    ]
    return chain, out
