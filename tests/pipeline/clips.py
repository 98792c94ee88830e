"""Short synthetic clips written by GStreamer for the source tests, and videos read back frame by frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dcuscope.core.gst import Gst, GstVideo
from dcuscope.plugins.frames import mapped_video

H264_MP4 = "x264enc speed-preset=ultrafast ! mp4mux"
MJPEG_MULTIPART = "jpegenc ! multipartmux"
"""A container with no index and no length: it can be played, not looped."""


def write_clip(path: Path, frames: int, encode: str = H264_MP4) -> Path:
    """``frames`` frames of a moving ball at 10 frames/s, 320x240, through ``encode`` into ``path``."""
    pipeline = Gst.parse_launch(
        f"videotestsrc num-buffers={frames} pattern=ball ! video/x-raw,width=320,height=240,framerate=10/1 "
        f'! {encode} ! filesink location="{path}"')
    pipeline.set_state(Gst.State.PLAYING)
    message = pipeline.get_bus().timed_pop_filtered(30 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    pipeline.set_state(Gst.State.NULL)
    assert message is not None and message.type == Gst.MessageType.EOS
    return path


def decode_video(path: Path) -> list[np.ndarray]:
    """Every frame of an MP4 as RGB arrays, decoded by GStreamer (proves the file plays)."""
    pipeline = Gst.parse_launch(
        f'filesrc location="{path}" ! qtdemux ! h264parse ! avdec_h264 ! videoconvert ! '
        "video/x-raw,format=RGB ! appsink name=out sync=false emit-signals=false"
    )
    out = pipeline.get_by_name("out")
    frames = []
    pipeline.set_state(Gst.State.PLAYING)
    while True:
        sample = out.emit("try-pull-sample", 10 * Gst.SECOND)
        if sample is None:
            break
        info = GstVideo.VideoInfo.new_from_caps(sample.get_caps())
        with mapped_video(sample.get_buffer(), info) as frame:
            frames.append(frame.copy())
    pipeline.set_state(Gst.State.NULL)
    return frames
