"""The convert element in real pipelines, checked against GStreamer's own videoconvert."""

from pathlib import Path

import numpy as np
import pytest

from dcuscope.core.gst import Gst, GstVideo
from dcuscope.plugins import convert, frames
from dcuscope.plugins.colorspace import image_from_memory
from dcuscope.plugins.frames import Detections, FrameId

CLIP = Path(__file__).resolve().parents[2] / "assets" / "media" / "vtest.avi"  # 768x576: SD, BT.601
RGB_CLIP = f"filesrc location={CLIP} ! decodebin ! videoconvert ! video/x-raw,format=RGB"


def register() -> None:
    name, rank, cls = convert.__gstelementfactory__
    if Gst.ElementFactory.find(name) is None:
        Gst.Element.register(None, name, rank, cls.__gtype__)


def planes(sample):
    """Copies of the planes of a sample, per its caps (offsets, strides)."""
    info = GstVideo.VideoInfo.new_from_caps(sample.get_caps())
    buf = sample.get_buffer()
    data = np.frombuffer(buf.extract_dup(0, buf.get_size()), np.uint8)
    img = image_from_memory(data, info.finfo.name, info.width, info.height, info.offset, info.stride)
    return [p.copy() for p in img.planes]


def pull(description: str, sinks=("ours", "ref"), n=3, push=None, caps=None):
    """Run ``description`` (appsinks named as in ``sinks``) and pull ``n`` samples from each."""
    register()
    pipeline = Gst.parse_launch(description)
    if push is not None:
        src = pipeline.get_by_name("src")
        src.set_property("caps", Gst.Caps.from_string(caps))
    assert pipeline.set_state(Gst.State.PLAYING) != Gst.StateChangeReturn.FAILURE
    if push is not None:
        for b in push:
            src.emit("push-buffer", b)
        src.emit("end-of-stream")
    out = {name: [] for name in sinks}
    try:
        for name in sinks:
            sink = pipeline.get_by_name(name)
            for _ in range(n):
                sample = sink.emit("try-pull-sample", 10 * Gst.SECOND)
                assert sample is not None, f"{name}: no sample"
                out[name].append(sample)
        msg = pipeline.get_bus().pop_filtered(Gst.MessageType.ERROR)
        assert msg is None, msg.parse_error()
    finally:
        pipeline.set_state(Gst.State.NULL)
    return out, pipeline


def side_by_side(upstream: str, ours: str, ref: str) -> str:
    sink = "appsink max-buffers=3 sync=false"
    return (f"{upstream} ! tee name=t t. ! queue ! {ours} ! {sink} name=ours "
            f"t. ! queue ! {ref} ! {sink} name=ref")


@pytest.mark.parametrize("fmt", ["I420", "NV12"])
def test_rgb_to_yuv420_matches_videoconvert_on_clip_frames(fmt):
    out, _ = pull(side_by_side(RGB_CLIP, f"convert format={fmt}", f"videoconvert ! video/x-raw,format={fmt}"))
    for ours, ref in zip(out["ours"], out["ref"]):
        assert ours.get_caps().get_structure(0).get_value("colorimetry") == "bt601"
        o, r = planes(ours), planes(ref)
        y = np.abs(o[0].astype(int) - r[0])
        assert y.max() <= 1  # same BT.601 limited-range luma, rounding apart
        uv = np.abs(np.concatenate([p.ravel() for p in o[1:]]).astype(int) - np.concatenate([p.ravel() for p in r[1:]]))
        # Chroma: OpenCV takes one sample per 2x2 block, videoconvert filters; equal on flat areas.
        assert uv.mean() < 0.6 and np.percentile(uv, 99) <= 3


@pytest.mark.parametrize("fmt", ["I420", "NV12"])
def test_yuv420_to_rgb_matches_videoconvert_on_clip_frames(fmt):
    upstream = f"{RGB_CLIP} ! videoconvert ! video/x-raw,format={fmt}"
    out, _ = pull(side_by_side(upstream, "convert format=RGB", "videoconvert ! video/x-raw,format=RGB"))
    for ours, ref in zip(out["ours"], out["ref"]):
        d = np.abs(planes(ours)[0].astype(int) - planes(ref)[0])
        # videoconvert's 8-bit fast path for YUV -> RGB reads about 2 levels low everywhere
        # (Y 128 -> 128 where BT.601 says 130.4); ours follows the formula (test_colorspace).
        assert d.mean() < 3 and np.percentile(d, 99) <= 8


def test_bt709_input_is_decoded_with_bt709():
    # videotestsrc at 1280x720 I420 is BT.709 (GStreamer's default colorimetry for HD).
    upstream = "videotestsrc num-buffers=2 pattern=smpte75 ! video/x-raw,format=I420,width=1280,height=720"
    out, _ = pull(side_by_side(upstream, "convert format=RGBx", "videoconvert ! video/x-raw,format=RGBx"), n=2)
    for ours, ref in zip(out["ours"], out["ref"]):
        d = np.abs(planes(ours)[0][..., :3].astype(int) - planes(ref)[0][..., :3])
        assert d.mean() < 3 and np.percentile(d, 99) <= 10  # decoding as BT.601: mean 8.4, p99 37


@pytest.mark.parametrize("fmt", ["RGBA", "I420", "NV12"])
def test_rgb_to_format_with_resize_matches_videoscale_and_videoconvert(fmt):
    colorimetry = ",colorimetry=bt601" if fmt != "RGBA" else ""
    out, _ = pull(side_by_side(
        RGB_CLIP, f"convert format={fmt} width=384 height=288",
        f"videoscale ! videoconvert ! video/x-raw,format={fmt},width=384,height=288{colorimetry}",
    ), n=2)
    for ours, ref in zip(out["ours"], out["ref"]):
        s = ours.get_caps().get_structure(0)
        assert (s.get_value("format"), s.get_value("width"), s.get_value("height")) == (fmt, 384, 288)
        o, r = planes(ours), planes(ref)
        for a, b in zip(o, r):
            assert a.shape == b.shape
            d = np.abs(a.astype(int) - b)
            assert d.mean() < 2.5, fmt  # area average vs GStreamer's filter: close on real frames


def test_same_caps_pass_through_untouched():
    out, pipeline = pull(
        "videotestsrc num-buffers=2 ! video/x-raw,format=RGBA,width=64,height=48 ! tee name=t "
        "t. ! queue ! convert name=c format=RGBA ! appsink name=ours t. ! queue ! appsink name=ref", n=2,
    )
    assert pipeline.get_by_name("c").is_passthrough()
    for ours, ref in zip(out["ours"], out["ref"]):
        assert ours.get_buffer().extract_dup(0, 64 * 48 * 4) == ref.get_buffer().extract_dup(0, 64 * 48 * 4)


def test_detections_scaled_and_identity_kept():
    w, h = 64, 48
    buffers = []
    for i in range(2):
        buf = Gst.Buffer.new_wrapped(np.full((h, w, 3), 30 * i, np.uint8).tobytes())
        buf.pts = i * Gst.SECOND // 10
        frames.write_frames(buf, [FrameId(2, i, 500 + i)])
        frames.write_objects(buf, Detections(
            slot=np.zeros(1, np.int32), cls=np.ones(1, np.int32), score=np.full(1, 0.5, np.float32),
            boxes=np.array([[8, 4, 40, 44]], np.float32), labels=["person"],
        ))
        buffers.append(buf)
    out, _ = pull("appsrc name=src format=time ! convert format=I420 width=32 height=96 ! appsink name=ours",
                  sinks=("ours",), n=2, push=buffers,
                  caps=f"video/x-raw,format=RGB,width={w},height={h},framerate=10/1")
    for i, sample in enumerate(out["ours"]):
        buf = sample.get_buffer()
        assert frames.read_frames(buf) == [FrameId(2, i, 500 + i)]
        dets = frames.read_objects(buf)
        np.testing.assert_allclose(dets.boxes, [[4, 8, 20, 88]])
        assert dets.labels == ["person"]
        assert abs(int(planes(sample)[0].mean()) - (16 + 30 * i * 219 // 255)) <= 1


def test_unknown_format_is_a_clear_error():
    register()
    pipeline = Gst.parse_launch("videotestsrc num-buffers=2 ! convert name=c format=YUY9 ! fakesink")
    try:
        assert pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE
        msg = pipeline.get_bus().timed_pop_filtered(Gst.SECOND, Gst.MessageType.ERROR)
        assert msg is not None
        err, _ = msg.parse_error()
        assert "c: unknown format 'YUY9'" in err.message and "NV12" in err.message
    finally:
        pipeline.set_state(Gst.State.NULL)
    with pytest.raises(ValueError, match="unknown format"):
        convert.check_format("rgba")


def test_a_buffer_smaller_than_its_caps_is_a_stream_error():
    register()
    pipeline = Gst.parse_launch("appsrc name=src format=time ! convert name=c format=I420 ! fakesink")
    src = pipeline.get_by_name("src")
    src.set_property("caps", Gst.Caps.from_string("video/x-raw,format=RGB,width=64,height=48,framerate=10/1"))
    try:
        pipeline.set_state(Gst.State.PLAYING)
        src.emit("push-buffer", Gst.Buffer.new_wrapped(bytes(64 * 47 * 3)))
        msg = pipeline.get_bus().timed_pop_filtered(5 * Gst.SECOND, Gst.MessageType.ERROR)
    finally:
        pipeline.set_state(Gst.State.NULL)
    assert msg is not None and "c: cannot convert a buffer of 9024 bytes as RGB 64x48" in msg.parse_error()[0].message


def test_yuv420_output_of_an_odd_size_is_refused_with_the_reason():
    register()
    pipeline = Gst.parse_launch(
        "videotestsrc num-buffers=1 ! video/x-raw,format=RGB,width=33,height=24 "
        "! convert name=c format=NV12 ! fakesink")
    try:
        pipeline.set_state(Gst.State.PLAYING)
        msg = pipeline.get_bus().timed_pop_filtered(5 * Gst.SECOND, Gst.MessageType.ERROR)
    finally:
        pipeline.set_state(Gst.State.NULL)
    assert msg is not None and "NV12 needs an even width and height, got 33x24" in msg.parse_error()[0].message
