"""Detector maths on synthetic tensors, model recognition, and the shipped models on a real frame."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from dcuscope.plugins.detection import (
    LETTERBOX_GREY, Letterbox, decode_centernet, decode_ssd, decode_yolo, hwc_to_chw_unit, letterbox_into, nms,
    resize_into,
)
from dcuscope.plugins.models import (
    COCO80_NAMES, DEFAULT_MODEL, MODELS_DIR, Detector, ModelError, default_labels, inspect_model, load_labels,
    open_session, select_providers,
)

SSD_MODEL = MODELS_DIR / "ssdlite_mobilenetv2_person.onnx"
VTEST = Path(__file__).resolve().parents[2] / "assets" / "media" / "vtest.avi"
CPU = ["CPUExecutionProvider"]


def read_rgb(path: Path, index: int) -> np.ndarray:
    cap = cv2.VideoCapture(str(path))
    cap.set(cv2.CAP_PROP_POS_FRAMES, index)
    ok, bgr = cap.read()
    cap.release()
    assert ok, f"cannot read frame {index} of {path}"
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


# --- NMS -----------------------------------------------------------------------------------


def test_nms_removes_duplicates_of_a_class_and_keeps_other_classes():
    boxes = np.array([[10, 10, 50, 50], [12, 11, 51, 52], [10, 10, 50, 50], [100, 100, 140, 140]], np.float32)
    scores = np.array([0.6, 0.9, 0.8, 0.5], np.float32)
    classes = np.array([0, 0, 1, 0], np.int32)
    keep = nms(boxes, scores, classes, 0.45)
    # box 0 overlaps the better box 1 of its class; box 2 overlaps it too but is another class
    assert keep.tolist() == [1, 2, 3]


def test_nms_iou_threshold_decides_partial_overlap():
    boxes = np.array([[0, 0, 10, 10], [5, 0, 15, 10]], np.float32)  # IoU = 50 / 150 = 1/3
    scores = np.array([0.9, 0.8], np.float32)
    classes = np.zeros(2, np.int32)
    assert nms(boxes, scores, classes, 0.3).tolist() == [0]
    assert nms(boxes, scores, classes, 0.4).tolist() == [0, 1]


def test_nms_keeps_classes_apart_even_for_negative_coordinates():
    boxes = np.array([[-50, -50, -10, -10], [-50, -50, -10, -10], [-49, -50, -10, -10]], np.float32)
    keep = nms(boxes, np.array([0.9, 0.8, 0.7], np.float32), np.array([0, 1, 0], np.int32), 0.45)
    assert keep.tolist() == [0, 1]


def test_nms_of_nothing():
    assert nms(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32), 0.5).size == 0


# --- preprocessing -------------------------------------------------------------------------


def test_letterbox_fit_and_inverse_for_a_wide_frame():
    box = Letterbox.fit(768, 576, 640, 640)
    assert (box.width, box.height, box.pad_x, box.pad_y) == (640, 480, 0, 80)
    in_input = np.array([[0, 80, 640, 560], [320, 320, 384, 400]], np.float32)
    np.testing.assert_allclose(box.to_frame(in_input), [[0, 0, 768, 576], [384, 288, 460.8, 384]], rtol=1e-5)


def test_letterbox_into_leaves_grey_bands_and_chw_scales_to_unit():
    frame = np.full((20, 40, 3), (255, 0, 128), np.uint8)
    canvas = np.full((16, 16, 3), LETTERBOX_GREY, np.uint8)
    box = Letterbox.fit(40, 20, 16, 16)
    assert (box.width, box.height, box.pad_x, box.pad_y) == (16, 8, 0, 4)
    letterbox_into(frame, canvas, box)
    assert (canvas[:4] == LETTERBOX_GREY).all() and (canvas[12:] == LETTERBOX_GREY).all()
    assert (canvas[4:12] == (255, 0, 128)).all()
    chw = np.empty((3, 16, 16), np.float32)
    hwc_to_chw_unit(canvas, chw)
    assert chw[0, 8, 8] == 1.0 and chw[1, 8, 8] == 0.0 and chw[2, 0, 0] == pytest.approx(114 / 255)


def test_resize_into_writes_the_destination():
    dst = np.zeros((3, 5, 3), np.uint8)
    resize_into(np.full((30, 50, 3), 7, np.uint8), dst)
    assert (dst == 7).all()


# --- decoders ------------------------------------------------------------------------------


def centernet_rows(*rows) -> np.ndarray:
    out = np.zeros((1, 100, 6), np.float32)
    out[0, : len(rows)] = rows
    return out


def test_centernet_maps_input_pixels_to_a_non_square_frame_and_applies_nms():
    det = centernet_rows(
        [64, 128, 128, 256, 0.9, 0],  # person
        [66, 130, 130, 258, 0.5, 0],  # the same person at a neighbouring peak
        [64, 128, 128, 256, 0.6, 2],  # a car at the same place: another class, kept
        [300, 300, 400, 400, 0.2, 0],  # below threshold
        [480, 500, 600, 530, 0.7, 7],  # runs past the input edge: clipped to the frame
    )
    objs = decode_centernet(det[0], 768, 576, 512, 512, threshold=0.3, iou=0.45)
    np.testing.assert_allclose(objs.boxes, [[96, 144, 192, 288], [720, 562.5, 768, 576], [96, 144, 192, 288]],
                               rtol=1e-5)
    np.testing.assert_allclose(objs.scores, [0.9, 0.7, 0.6])
    assert objs.classes.tolist() == [0, 7, 2]


def test_centernet_threshold_filters_everything():
    objs = decode_centernet(centernet_rows([0, 0, 10, 10, 0.2, 0])[0], 640, 272, 512, 512, 0.3, 0.45)
    assert len(objs.boxes) == 0 and objs.boxes.shape == (0, 4)


def test_ssd_normalised_yxyx_to_frame_pixels_and_zero_based_classes():
    boxes = np.zeros((100, 4), np.float32)
    scores = np.zeros(100, np.float32)
    classes = np.ones(100, np.float32)
    boxes[:4] = [[0.25, 0.5, 0.75, 1.0], [0.0, 0.0, 0.5, 0.25], [0.1, 0.1, 0.2, 0.2], [0.3, 0.3, 0.6, 0.6]]
    scores[:4] = [0.8, 0.95, 0.1, 0.9]
    classes[1] = 3
    # num = 3: the fourth row is past num_detections and must be ignored whatever its score
    objs = decode_ssd(np.float32(3), boxes, scores, classes, 640, 272, threshold=0.3)
    np.testing.assert_allclose(objs.boxes, [[0, 0, 160, 136], [320, 68, 640, 204]], rtol=1e-5)
    assert objs.classes.tolist() == [2, 0]
    np.testing.assert_allclose(objs.scores, [0.95, 0.8])


def yolo_output(num_classes: int, anchors: int, *rows) -> np.ndarray:
    """(4 + C, N) head with ``rows`` = (anchor, cx, cy, w, h, class, score)."""
    out = np.zeros((4 + num_classes, anchors), np.float32)
    for anchor, cx, cy, w, h, cls, score in rows:
        out[:4, anchor] = cx, cy, w, h
        out[4 + cls, anchor] = score
    return out


def test_yolo_undoes_the_letterbox_picks_best_class_and_applies_nms():
    box = Letterbox.fit(640, 272, 640, 640)  # scale 1, bands of 184 above and below
    assert (box.scale, box.pad_y) == (1.0, 184)
    out = yolo_output(3, 50,
                      (7, 100, 284, 40, 80, 1, 0.9),  # frame box 80,60 - 120,140
                      (9, 102, 286, 40, 80, 1, 0.6),  # duplicate of anchor 7
                      (11, 100, 284, 40, 80, 2, 0.7),  # same place, other class
                      (13, 320, 320, 10, 10, 0, 0.2))  # below threshold
    out[4 + 0, 7] = 0.5  # a weaker second class on anchor 7: the best class wins
    objs = decode_yolo(out, box, 640, 272, threshold=0.3, iou=0.45)
    np.testing.assert_allclose(objs.boxes, [[80, 60, 120, 140], [80, 60, 120, 140]], rtol=1e-5)
    assert objs.classes.tolist() == [1, 2]
    np.testing.assert_allclose(objs.scores, [0.9, 0.7])


def test_yolo_scales_back_a_downscaled_frame():
    box = Letterbox.fit(1280, 720, 640, 640)  # scale 0.5, bands of 140
    out = yolo_output(1, 10, (0, 320, 320, 64, 32, 0, 0.8))
    objs = decode_yolo(out, box, 1280, 720, 0.3, 0.45)
    np.testing.assert_allclose(objs.boxes, [[576, 328, 704, 392]], rtol=1e-5)


def test_yolo_caps_candidates_before_nms():
    out = yolo_output(1, 2000, *[(i, 5 + i % 600, 5 + i // 600 * 20, 4, 4, 0, 0.5 + i / 10000) for i in range(2000)])
    objs = decode_yolo(out, Letterbox.fit(640, 640, 640, 640), 640, 640, 0.3, 0.45, max_candidates=100)
    assert len(objs.scores) <= 100 and objs.scores.min() >= 0.5 + 1900 / 10000 - 1e-6


# --- models: recognition, errors, labels ---------------------------------------------------


@pytest.fixture(scope="module")
def sessions():
    return {"centernet": open_session(DEFAULT_MODEL, CPU), "ssd": open_session(SSD_MODEL, CPU)}


def test_shipped_models_are_recognised(sessions):
    cn = inspect_model(sessions["centernet"])
    assert (cn.decoder, cn.input_size, cn.batch, cn.output_names) == ("centernet", (512, 512), 1,
                                                                      ("tower_0/detections",))
    ssd = inspect_model(sessions["ssd"])
    assert (ssd.decoder, ssd.input_size, ssd.batch) == ("ssd", (300, 300), None)
    assert default_labels(cn)[:3] == ["person", "bicycle", "car"] and len(default_labels(cn)) == 80
    assert default_labels(ssd) == ["person"]


def test_a_decoder_that_does_not_fit_names_the_model(sessions):
    with pytest.raises(ModelError, match="ssdlite_mobilenetv2_person.onnx.*decoder 'yolo'"):
        inspect_model(sessions["ssd"], "yolo", SSD_MODEL)
    with pytest.raises(ModelError, match="not one of"):
        inspect_model(sessions["ssd"], "retinanet", SSD_MODEL)


def test_missing_and_non_onnx_files_name_the_file(tmp_path):
    with pytest.raises(ModelError, match="nothere.onnx does not exist") as err:
        open_session(tmp_path / "nothere.onnx", CPU)
    assert err.value.code == "not-found"
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"this is not a protobuf")
    with pytest.raises(ModelError, match=f"{junk} is not a usable ONNX model") as err:
        open_session(junk, CPU)
    assert err.value.code == "unreadable"


def test_labels_file_and_provider_fallback(tmp_path):
    names = load_labels(COCO80_NAMES)
    assert len(names) == 80 and names[9] == "traffic light" and names[79] == "toothbrush"
    with pytest.raises(ModelError, match="nolabels.txt"):
        load_labels(tmp_path / "nolabels.txt")
    use, missing = select_providers("NoSuchExecutionProvider, CPUExecutionProvider")
    assert use == ["CPUExecutionProvider"] and missing == ["NoSuchExecutionProvider"]


# --- the shipped models on a real frame ----------------------------------------------------


@pytest.fixture(scope="module")
def frame300() -> np.ndarray:
    return read_rgb(VTEST, 300)


@pytest.mark.parametrize("model", ["centernet", "ssd"])
def test_real_frame_has_people(sessions, frame300, model):
    session = sessions[model]
    detector = Detector(session, inspect_model(session))
    small = cv2.resize(frame300, (384, 288))  # a second, smaller frame: a batch of two sizes
    found = detector.detect([frame300, small], threshold=0.3, iou=0.45)
    assert len(found) == 2
    people = found[0].boxes[found[0].classes == 0]
    assert len(people) >= 4, found[0]
    assert (people[:, :2] >= 0).all() and (people[:, 2] <= 768).all() and (people[:, 3] <= 576).all()
    # pedestrians are taller than wide, of a plausible size for this clip
    w, h = people[:, 2] - people[:, 0], people[:, 3] - people[:, 1]
    assert (h > w).mean() >= 0.75 and (h > 15).all() and (h < 300).all()
    # the same people, found in the half-size frame, at half the coordinates
    half = found[1].boxes[found[1].classes == 0] * 2
    matched = [np.abs(half - p).max(axis=1).min() < 30 for p in people]
    assert np.mean(matched) >= 0.5
