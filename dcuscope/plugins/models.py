"""ONNX Runtime side of the infer element: sessions, providers, model layouts, the detector.

A model is recognised by its inputs and outputs (:func:`inspect_model`), which gives one of
three decoders of :mod:`dcuscope.plugins.detection`. :class:`Detector` owns the session and the
preallocated input tensors and turns a list of RGB frames into :class:`Objects` per frame.
Errors a user can cause (missing file, not an ONNX model, unknown layout, bad labels file)
raise :class:`ModelError` with a message that names the file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

# ONNX Runtime 1.30 and later send telemetry to Microsoft from Linux too, and keep a device id in
# ~/.cache, unless this is set before they load (the user may set it to 0). A measurement tool on
# vehicles and robots sends nothing anywhere by itself.
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
import onnxruntime as ort  # noqa: E402 - after the setting above

from dcuscope.core.datadir import DATA
from dcuscope.core.errors import DcuscopeError
from dcuscope.plugins.detection import (
    LETTERBOX_GREY, Letterbox, Objects, decode_centernet, decode_ssd, decode_yolo, hwc_to_chw_unit,
    letterbox_into, resize_into,
)

MODELS_DIR = DATA / "assets" / "models"
DEFAULT_MODEL = MODELS_DIR / "centernet_mobilenetv3_coco80.onnx"
COCO80_NAMES = MODELS_DIR / "coco80.names"
DECODERS = ("auto", "centernet", "ssd", "yolo")
CPU = "CPUExecutionProvider"
CUDA = "CUDAExecutionProvider"

# network input (width, height) when the model leaves it dynamic: what each family was trained on
DEFAULT_INPUT_SIZE = {"centernet": (512, 512), "ssd": (300, 300), "yolo": (640, 640)}
SSD_OUTPUTS = ("num_detections", "detection_boxes", "detection_scores", "detection_classes")


class ModelError(DcuscopeError):
    """A model, labels file or decoder choice that cannot be used; ``code`` says which kind."""

    def __init__(self, message: str, code: str = "settings"):
        super().__init__(message)
        self.code = code  # "not-found" | "unreadable" | "settings"


@dataclass(frozen=True)
class ModelLayout:
    """What a decoder needs to know about a model's tensors."""

    decoder: str
    input_name: str
    input_size: tuple[int, int]  # (width, height) of the network input
    batch: int | None  # fixed batch dimension, None when dynamic
    output_names: tuple[str, ...]  # in the order the decoder takes them
    num_classes: int | None  # None when the layout does not tell


def select_providers(requested: str) -> tuple[list[str], list[str]]:
    """(providers to use, requested ones this onnxruntime lacks); CPU always ends the list."""
    names = [p.strip() for p in requested.split(",") if p.strip()]
    available = set(ort.get_available_providers())
    use = [p for p in names if p in available]
    missing = [p for p in names if p not in available]
    if CPU not in use:
        use.append(CPU)
    return use, missing


def open_session(path: str | Path, providers: Sequence[str], threads: int = 0,
                 spin_wait: bool = False) -> ort.InferenceSession:
    """An inference session on ``path``; raises :class:`ModelError` naming the file.

    ``spin_wait``: ONNX Runtime's worker threads spin after each run by default. Between two
    batches of a pipeline that time is the other stages' (decoders, tiler, convert): with a
    batch every 20 ms of other work, spinning took 1.3-1.8x the CPU, and the 4-camera
    pipeline ran slower with it (BENCHMARKS.md, "Inference on the CPU"; benchmarks/bench_infer_cpu.py).
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"model file {path} does not exist", "not-found")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin_wait else "0")
    options.log_severity_level = 3  # ORT's own warnings would duplicate ours on stderr
    if CUDA in providers and hasattr(ort, "preload_dlls"):
        # onnxruntime-gpu finds CUDA and cuDNN installed as pip packages (nvidia-*, or PyTorch's)
        # only when they are loaded first; system-wide installs are found either way.
        ort.preload_dlls()
    try:
        return ort.InferenceSession(str(path), sess_options=options, providers=list(providers))
    except Exception as exc:  # ORT raises several unrelated types for a bad file
        raise ModelError(f"model file {path} is not a usable ONNX model: {exc}", "unreadable") from exc


def check_model(path: str | Path, decoder: str = "auto") -> ModelLayout:
    """The layout of the model at ``path``, from a CPU session opened only to look at it: the
    check, when a configuration is loaded, that ``infer`` will be able to use the file (a bad one
    would otherwise stop the pipeline once it starts). :class:`ModelError` naming the file."""
    return inspect_model(open_session(path, [CPU], threads=1), decoder, path)


def _short(name: str) -> str:
    return name.split(":")[0]


def _dim(value) -> int | None:
    return value if isinstance(value, int) and value > 0 else None


def _describe(session: ort.InferenceSession) -> str:
    ios = [f"input {i.name} {i.shape} {i.type}" for i in session.get_inputs()]
    ios += [f"output {o.name} {o.shape}" for o in session.get_outputs()]
    return "; ".join(ios)


def _match(decoder: str, session: ort.InferenceSession) -> ModelLayout | None:
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if len(inputs) != 1 or len(inputs[0].shape) != 4:
        return None
    inp, shape = inputs[0], inputs[0].shape
    batch = _dim(shape[0])
    if decoder == "ssd":
        by_name = {_short(o.name): o.name for o in outputs}
        if inp.type != "tensor(uint8)" or shape[3] != 3 or not all(n in by_name for n in SSD_OUTPUTS):
            return None
        h, w = _dim(shape[1]), _dim(shape[2])
        size = (w, h) if w and h else DEFAULT_INPUT_SIZE["ssd"]
        return ModelLayout("ssd", inp.name, size, batch, tuple(by_name[n] for n in SSD_OUTPUTS), None)
    if inp.type != "tensor(float)":
        return None
    if decoder == "centernet":
        dets = [o for o in outputs if len(o.shape) == 3 and o.shape[2] == 6]
        if shape[3] != 3 or len(dets) != 1:
            return None
        h, w = _dim(shape[1]), _dim(shape[2])
        size = (w, h) if w and h else DEFAULT_INPUT_SIZE["centernet"]
        return ModelLayout("centernet", inp.name, size, batch, (dets[0].name,), None)
    if decoder == "yolo":
        out = outputs[0].shape
        if shape[1] != 3 or len(out) != 3 or not _dim(out[1]) or out[1] <= 4:
            return None
        if _dim(out[2]) and out[2] <= out[1]:  # (N, 4 + C) or a post-NMS head: another layout
            return None
        h, w = _dim(shape[2]), _dim(shape[3])
        size = (w, h) if w and h else DEFAULT_INPUT_SIZE["yolo"]
        return ModelLayout("yolo", inp.name, size, batch, (outputs[0].name,), out[1] - 4)
    raise ValueError(f"unknown decoder {decoder!r}")


def inspect_model(session: ort.InferenceSession, decoder: str = "auto", path: str | Path = "") -> ModelLayout:
    """The layout of ``session`` for ``decoder`` ("auto": the first decoder that fits)."""
    if decoder not in DECODERS:
        raise ModelError(f"decoder {decoder!r} is not one of {', '.join(DECODERS)}")
    for name in DECODERS[1:] if decoder == "auto" else (decoder,):
        layout = _match(name, session)
        if layout is not None:
            return layout
    wanted = "any known decoder (centernet, ssd, yolo)" if decoder == "auto" else f"decoder {decoder!r}"
    raise ModelError(f"model file {path} does not have the layout of {wanted}: {_describe(session)}")


def load_labels(path: str | Path) -> list[str]:
    """One class name per line; blank lines end nothing but are kept as empty names."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8").rstrip("\n").split("\n")
    except OSError as exc:
        raise ModelError(f"labels file {path} cannot be read: {exc.strerror}", "not-found") from exc


def default_labels(layout: ModelLayout) -> list[str]:
    """Labels of the shipped models' families when the user gives no labels file."""
    if layout.decoder == "ssd":
        return ["person"]
    if layout.decoder == "centernet" or layout.num_classes == 80:
        return load_labels(COCO80_NAMES)
    return [f"class{i}" for i in range(layout.num_classes or 0)]


class Detector:
    """A session plus its preallocated input tensors; frames in, :class:`Objects` out."""

    def __init__(self, session: ort.InferenceSession, layout: ModelLayout):
        self.session = session
        self.layout = layout
        w, h = layout.input_size
        self._tensor = np.zeros((0,), np.float32)
        self._scratch = np.zeros((h, w, 3), np.uint8)  # resized frame before conversion
        self._boxes: dict[tuple[int, int], Letterbox] = {}
        self._grey_for: tuple[int, int] | None = None

    def _input(self, n: int) -> np.ndarray:
        """An input tensor of batch ``n``, reallocated only when a larger one is needed."""
        w, h = self.layout.input_size
        per_frame = {"centernet": ((h, w, 3), np.float32), "ssd": ((h, w, 3), np.uint8),
                     "yolo": ((3, h, w), np.float32)}
        shape, dtype = per_frame[self.layout.decoder]
        if self._tensor.ndim != 4 or self._tensor.shape[0] < n:
            self._tensor = np.zeros((n, *shape), dtype)
        return self._tensor[:n]

    def _letterbox(self, frame_w: int, frame_h: int) -> Letterbox:
        key = (frame_w, frame_h)
        if key not in self._boxes:
            self._boxes[key] = Letterbox.fit(frame_w, frame_h, *self.layout.input_size)
        if self._grey_for != key:  # bands of another frame size would leave old pixels
            self._scratch[...] = LETTERBOX_GREY
            self._grey_for = key
        return self._boxes[key]

    def _prepare(self, frame: np.ndarray, dst: np.ndarray) -> None:
        decoder = self.layout.decoder
        if decoder == "ssd":
            resize_into(frame, dst)
        elif decoder == "centernet":
            np.copyto(dst, resize_into(frame, self._scratch))
        else:
            letterbox_into(frame, self._scratch, self._letterbox(frame.shape[1], frame.shape[0]))
            hwc_to_chw_unit(self._scratch, dst)

    def _decode(self, outputs: list[np.ndarray], i: int, frame_w: int, frame_h: int, threshold: float,
                iou: float) -> Objects:
        decoder, (in_w, in_h) = self.layout.decoder, self.layout.input_size
        if decoder == "centernet":
            return decode_centernet(outputs[0][i], frame_w, frame_h, in_w, in_h, threshold, iou)
        if decoder == "ssd":
            num, boxes, scores, classes = (o[i] for o in outputs)
            return decode_ssd(num, boxes, scores, classes, frame_w, frame_h, threshold)
        return decode_yolo(outputs[0][i], self._letterbox(frame_w, frame_h), frame_w, frame_h, threshold, iou)

    def detect(self, frames: Sequence[np.ndarray], threshold: float, iou: float) -> list[Objects]:
        """Objects of each (H, W, 3) uint8 RGB frame, in frame pixels, in frame order.

        A model with a dynamic batch dimension runs once for all frames; one with a fixed
        batch runs per chunk of that size (a short last chunk is padded with stale data whose
        results are dropped).
        """
        step = len(frames) if self.layout.batch is None else self.layout.batch
        found: list[Objects] = []
        for start in range(0, len(frames), max(step, 1)):
            chunk = frames[start : start + step]
            tensor = self._input(step)
            for frame, dst in zip(chunk, tensor):
                self._prepare(frame, dst)
            outputs = self.session.run(list(self.layout.output_names), {self.layout.input_name: tensor})
            for i, frame in enumerate(chunk):
                found.append(self._decode(outputs, i, frame.shape[1], frame.shape[0], threshold, iou))
        return found
