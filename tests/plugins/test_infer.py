"""The infer element in real pipelines: appsrc (batches of real frames) ! infer ! appsink."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from dcuscope.core.gst import Gst
from dcuscope.plugins.frames import OBJECTS_CAPS, FrameId, batch_caps, read_frames, read_objects, write_frames
from dcuscope.plugins.infer import Infer
from dcuscope.plugins.models import MODELS_DIR

VTEST = Path(__file__).resolve().parents[2] / "assets" / "media" / "vtest.avi"
SSD_MODEL = MODELS_DIR / "ssdlite_mobilenetv2_person.onnx"
W, H = 768, 576


@pytest.fixture(scope="module", autouse=True)
def registered():
    if Gst.ElementFactory.find("infer") is None:
        Gst.Element.register(None, "infer", Gst.Rank.NONE, Infer.__gtype__)


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    """vtest.avi frames 300 and 301, RGB."""
    cap = cv2.VideoCapture(str(VTEST))
    cap.set(cv2.CAP_PROP_POS_FRAMES, 300)
    out = []
    for _ in range(2):
        ok, bgr = cap.read()
        assert ok
        out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    cap.release()
    return out


def batch(images: list[np.ndarray], first_frame: int = 0) -> Gst.Buffer:
    """A batch buffer: one GstMemory per frame, plus the frames' identity."""
    buf = Gst.Buffer.new()
    for image in images:
        buf.append_memory(Gst.Buffer.new_wrapped(np.ascontiguousarray(image).tobytes()).get_memory(0))
    write_frames(buf, [FrameId(slot, first_frame + slot, 1000 + slot) for slot in range(len(images))])
    return buf


def run(batches: list[Gst.Buffer], size: tuple[int, int], batch_size: int, **props) -> tuple[list[Gst.Buffer], list]:
    """Push ``batches`` through ``infer`` with ``props``; (output buffers, bus errors and warnings)."""
    pipeline = Gst.parse_launch("appsrc name=src format=time ! infer name=infer ! appsink name=sink sync=false")
    src, infer, sink = (pipeline.get_by_name(n) for n in ("src", "infer", "sink"))
    src.set_property("caps", batch_caps(size[0], size[1], batch_size, (10, 1)))
    for name, value in props.items():
        infer.set_property(name.replace("_", "-"), value)
    bus = pipeline.get_bus()
    outs, messages = [], []
    try:
        if pipeline.set_state(Gst.State.PLAYING) != Gst.StateChangeReturn.FAILURE:
            for i, buf in enumerate(batches):
                buf.pts = i * Gst.SECOND // 10
                src.emit("push-buffer", buf)
            src.emit("end-of-stream")
            for _ in batches:
                sample = sink.emit("try-pull-sample", 30 * Gst.SECOND)
                if sample is None:
                    break
                outs.append(sample.get_buffer())
        kinds = Gst.MessageType.ERROR | Gst.MessageType.WARNING
        while (msg := bus.pop_filtered(kinds)) is not None:
            messages.append(msg)
    finally:
        pipeline.set_state(Gst.State.NULL)
    return outs, messages


def errors(messages) -> list[str]:
    return [m.parse_error()[0].message for m in messages if m.type == Gst.MessageType.ERROR]


@pytest.mark.parametrize("model", ["centernet", "ssd"])
def test_people_in_a_batch_of_two_real_frames(frames, model):
    props = {"model": str(SSD_MODEL)} if model == "ssd" else {}
    outs, messages = run([batch(frames, first_frame=300)], (W, H), 2, **props)
    assert errors(messages) == [] and len(outs) == 1
    dets = read_objects(outs[0])
    for slot in (0, 1):
        people = dets.for_slot(slot)
        assert (people.cls == 0).sum() >= 4, people
        assert all(label == "person" for label, c in zip(people.labels, people.cls) if c == 0)
    assert (dets.boxes[:, :2] >= 0).all() and (dets.boxes[:, 2] <= W).all() and (dets.boxes[:, 3] <= H).all()
    assert (dets.boxes[:, 2:] > dets.boxes[:, :2]).all()
    assert (dets.score >= 0.3).all()
    # the identity and the frames pass through untouched
    assert [f.frame for f in read_frames(outs[0])] == [300, 301]
    assert outs[0].n_memory() == 2
    ok, info = outs[0].peek_memory(1).map(Gst.MapFlags.READ)
    assert np.array_equal(np.frombuffer(info.data, np.uint8).reshape(H, W, 3), frames[1])
    outs[0].peek_memory(1).unmap(info)


def test_a_short_batch_and_a_higher_threshold(frames):
    # caps say 4 frames, the buffer holds 1: only slot 0 may appear
    outs, messages = run([batch(frames[:1])], (W, H), 4, model=str(SSD_MODEL), threshold=0.8)
    assert errors(messages) == []
    dets = read_objects(outs[0])
    assert set(dets.slot.tolist()) == {0} and (dets.score >= 0.8).all() and len(dets) >= 1


def test_interval_skips_every_other_batch():
    small = [np.full((48, 64, 3), 90, np.uint8)]
    outs, messages = run([batch(small, i) for i in range(4)], (64, 48), 1, model=str(SSD_MODEL), interval=1)
    assert errors(messages) == [] and len(outs) == 4
    has_meta = [b.get_reference_timestamp_meta(OBJECTS_CAPS) is not None for b in outs]
    assert has_meta == [True, False, True, False]


@pytest.mark.parametrize("case", ["missing", "junk", "wrong-decoder", "labels"])
def test_unusable_model_posts_an_error_naming_property_and_path(tmp_path, case):
    props = {"model": str(tmp_path / "no-such-model.onnx")}
    if case == "junk":
        props["model"] = str(tmp_path / "junk.onnx")
        Path(props["model"]).write_bytes(b"not an onnx model at all")
    elif case == "wrong-decoder":
        props = {"model": str(SSD_MODEL), "decoder": "yolo"}
    elif case == "labels":
        props = {"model": str(SSD_MODEL), "labels": str(tmp_path / "no-labels.txt")}
    outs, messages = run([batch([np.zeros((8, 8, 3), np.uint8)])], (8, 8), 1, **props)
    assert outs == []
    (text,) = errors(messages)
    prop = "labels" if case == "labels" else "model"
    assert f'property "{prop}"' in text
    assert (props["labels"] if case == "labels" else props["model"]) in text
    if case == "wrong-decoder":
        assert "decoder 'yolo'" in text


def test_unknown_decoder_and_unavailable_provider():
    outs, messages = run([batch([np.zeros((8, 8, 3), np.uint8)])], (8, 8), 1, model=str(SSD_MODEL),
                         decoder="retinanet")
    assert outs == [] and 'property "decoder"' in errors(messages)[0]
    outs, messages = run([batch([np.zeros((8, 8, 3), np.uint8)])], (8, 8), 1, model=str(SSD_MODEL),
                         providers="NoSuchExecutionProvider,CPUExecutionProvider")
    assert len(outs) == 1 and errors(messages) == []
    (warning,) = [m.parse_warning()[0].message for m in messages if m.type == Gst.MessageType.WARNING]
    assert "NoSuchExecutionProvider not available" in warning


def test_properties_are_gstreamer_like():
    infer = Gst.ElementFactory.make("infer", None)
    assert infer.get_property("threshold") == pytest.approx(0.3)
    assert infer.get_property("nms-iou") == pytest.approx(0.45)
    assert infer.get_property("decoder") == "auto" and infer.get_property("interval") == 0
    assert Path(infer.get_property("model")).is_file()
    spec = infer.find_property("threshold")
    assert (spec.minimum, spec.maximum) == (0.0, 1.0) and spec.nick == "Threshold"
    with pytest.raises(TypeError):
        infer.set_property("no-such-property", 1)


# --- a user's Ultralytics YOLO export, made up as a tiny ONNX graph ------------------------


def tiny_yolo(path: Path, head: np.ndarray) -> None:
    """A model with Ultralytics' layout (images [1,3,640,640] -> output0 [1,4+C,N]) whose head
    is ``head`` whatever the image (plus 0 x its mean, so the input is really consumed)."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    graph = helper.make_graph(
        [
            helper.make_node("ReduceMean", ["images"], ["mean"], keepdims=0),
            helper.make_node("Mul", ["mean", "zero"], ["nothing"]),
            helper.make_node("Add", ["head", "nothing"], ["output0"]),
        ],
        "tiny_yolo",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, 640, 640])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(head.shape))],
        [numpy_helper.from_array(head, "head"), numpy_helper.from_array(np.zeros((), np.float32), "zero")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def test_yolo_layout_model_is_recognised_and_mapped_to_the_frame(tmp_path):
    head = np.zeros((1, 4 + 2, 64), np.float32)
    head[0, :4, 5] = 320, 320, 64, 128  # input pixels
    head[0, 4 + 1, 5] = 0.9  # class 1
    head[0, :4, 6] = 322, 321, 64, 128  # a duplicate, weaker
    head[0, 4 + 1, 6] = 0.6
    tiny_yolo(tmp_path / "yolo.onnx", head)
    (tmp_path / "pets.names").write_text("cat\ndog\n")
    outs, messages = run([batch([np.zeros((H, W, 3), np.uint8)] * 2)], (W, H), 2,
                         model=str(tmp_path / "yolo.onnx"), labels=str(tmp_path / "pets.names"))
    assert errors(messages) == []
    dets = read_objects(outs[0])
    assert dets.slot.tolist() == [0, 1] and dets.labels == ["dog", "dog"] and dets.cls.tolist() == [1, 1]
    # 768x576 letterboxed into 640x640: scale 5/6, bands of 80 rows above and below
    np.testing.assert_allclose(dets.boxes[0], [345.6, 211.2, 422.4, 364.8], atol=0.02)
