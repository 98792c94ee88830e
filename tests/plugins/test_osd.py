"""The osd element in real pipelines: smoke tests and pixels where the boxes are."""

import numpy as np
import pytest

from dcuscope.core.gst import Gst
from dcuscope.plugins import convert, frames, osd
from dcuscope.plugins.drawing import class_color
from dcuscope.plugins.frames import Detections, FrameId

W, H = 160, 120


def register() -> None:
    for module in (convert, osd):
        name, rank, cls = module.__gstelementfactory__
        if Gst.ElementFactory.find(name) is None:
            Gst.Element.register(None, name, rank, cls.__gtype__)


def run_to_eos(description: str) -> None:
    register()
    pipeline = Gst.parse_launch(description)
    try:
        assert pipeline.set_state(Gst.State.PLAYING) != Gst.StateChangeReturn.FAILURE
        msg = pipeline.get_bus().timed_pop_filtered(10 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
        assert msg is not None and msg.type == Gst.MessageType.EOS, msg and msg.parse_error()
    finally:
        pipeline.set_state(Gst.State.NULL)


@pytest.mark.parametrize("chain", [
    "convert format=RGBA ! osd",
    "convert format=BGRx ! osd display-clock=true line-width=4 font-scale=0.8",
    "osd display-text=false",
])
def test_smoke(chain):
    run_to_eos(f"videotestsrc num-buffers=5 ! video/x-raw,format=RGB,width=320,height=240 ! {chain} ! fakesink")


def draw(fmt: str, props: str = "", with_objects: bool = True, value: int = 40):
    """Push one flat frame of ``fmt`` with two boxes through osd; return the output pixels."""
    register()
    channels = 3 if fmt in ("RGB", "BGR") else 4
    buf = Gst.Buffer.new_wrapped(np.full((H, W, channels), value, np.uint8).tobytes())
    buf.pts = 0
    frames.write_frames(buf, [FrameId(0, 0, 1)])
    if with_objects:
        frames.write_objects(buf, Detections(
            slot=np.zeros(2, np.int32), cls=np.array([0, 3], np.int32), score=np.array([0.9, 0.6], np.float32),
            boxes=np.array([[20, 40, 70, 100], [90, 30, 150, 90]], np.float32), labels=["person", "car"],
        ))
    pipeline = Gst.parse_launch(f"appsrc name=src format=time ! osd {props} ! appsink name=sink")
    src, sink = pipeline.get_by_name("src"), pipeline.get_by_name("sink")
    src.set_property("caps", Gst.Caps.from_string(f"video/x-raw,format={fmt},width={W},height={H},framerate=10/1"))
    try:
        assert pipeline.set_state(Gst.State.PLAYING) != Gst.StateChangeReturn.FAILURE
        src.emit("push-buffer", buf)
        src.emit("end-of-stream")
        sample = sink.emit("try-pull-sample", 5 * Gst.SECOND)
        assert sample is not None
        out = sample.get_buffer()
        assert frames.read_frames(out) == [FrameId(0, 0, 1)]
        return np.frombuffer(out.extract_dup(0, out.get_size()), np.uint8).reshape(H, W, channels)
    finally:
        pipeline.set_state(Gst.State.NULL)


@pytest.mark.parametrize("fmt", ["RGBA", "BGRx", "RGB", "BGR"])
def test_boxes_drawn_where_the_detections_are_in_class_colours(fmt):
    img = draw(fmt, "display-text=false line-width=2")
    for (x1, y1, x2, y2), cls in (((20, 40, 70, 100), 0), ((90, 30, 150, 90), 3)):
        colour = np.array(class_color(cls, fmt), np.uint8)
        for y, x in ((y1, (x1 + x2) // 2), (y2, (x1 + x2) // 2), ((y1 + y2) // 2, x1), ((y1 + y2) // 2, x2)):
            assert (img[y, x] == colour).all(), (fmt, cls, y, x)
        assert (img[y1 + 2 : y2 - 1, x1 + 2 : x2 - 1] == 40).all()  # inside untouched
    assert (img[:25, :] == 40).all() and (img[105:, :] == 40).all()  # away from the boxes


def test_labels_drawn_above_boxes_when_text_is_on():
    with_text = draw("RGBA", "display-text=true")
    without = draw("RGBA", "display-text=false")
    changed = np.any(with_text != without, axis=-1)
    ys, xs = np.nonzero(changed)
    assert changed.sum() > 200
    assert ys.max() < 40  # all text sits above the boxes (first box top 40, second 30)
    assert changed[18:30, 90:150].any() and changed[28:40, 20:70].any()


def test_clock_only_changes_the_top_left_corner():
    img = draw("RGBx", "display-clock=true", with_objects=False)
    changed = np.any(img != 40, axis=-1)
    ys, xs = np.nonzero(changed)
    assert changed.sum() > 100 and ys.max() < 30 and xs.max() < 130


def test_no_detections_no_clock_leaves_the_frame_alone():
    assert (draw("BGRA", with_objects=False) == 40).all()


def test_properties_have_gstreamer_defaults_and_ranges():
    register()
    el = Gst.ElementFactory.make("osd")
    assert el.get_property("display-text") is True
    assert el.get_property("line-width") == 2
    assert el.get_property("display-clock") is False
    assert el.get_property("font-scale") == pytest.approx(0.5)
    spec = el.find_property("line-width")
    assert (spec.minimum, spec.maximum) == (1, 32)
    with pytest.raises(TypeError):
        el.set_property("colour", 1)
