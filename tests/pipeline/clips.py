"""Short synthetic clips written by GStreamer for the source tests: a few seconds of a test pattern."""

from __future__ import annotations

from pathlib import Path

from core.gst import Gst

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
