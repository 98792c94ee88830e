"""infer: runs an ONNX detector over every frame of a batch (DeepStream's nvinfer).

In place: the batch passes through untouched and gains one objects meta (see
:mod:`dcuscope.plugins.frames`) holding the detections of all its frames, boxes in pixels of the
batch frame, ``slot`` = index of the frame in the batch. ``interval`` skips batches like
nvinfer's; a skipped batch carries no objects meta. The model is recognised by its inputs and
outputs (CenterNet, TF SSD, Ultralytics YOLOv8/v11) unless ``decoder`` names one.

    gst-launch-1.0 mux name=m batch-size=2 width=768 height=576 ! \\
        infer model=assets/models/ssdlite_mobilenetv2_person.onnx threshold=0.4 ! fakesink \\
        filesrc location=assets/media/vtest.avi ! decodebin ! videoconvert ! video/x-raw,format=RGB ! \\
        identity eos-after=20 ! framestamp ! m.sink_0 \\
        videotestsrc num-buffers=20 ! video/x-raw,format=RGB,width=768,height=576 ! framestamp source-id=1 ! m.sink_1
"""

from collections import Counter

import numpy as np

from dcuscope.core.gst import GLib, GObject, Gst, GstBase
from dcuscope.plugins.detection import Objects
from dcuscope.plugins.frames import BATCH_TEMPLATE_CAPS, BatchLayout, Detections, mapped_batch, write_objects
from dcuscope.plugins.models import (
    DECODERS, DEFAULT_MODEL, Detector, ModelError, default_labels, inspect_model, load_labels, open_session,
    select_providers,
)
from dcuscope.plugins.properties import AttributeProperties

DEFAULT_DECODER = "auto"
DEFAULT_THRESHOLD = 0.3
DEFAULT_NMS_IOU = 0.45
DEFAULT_INTERVAL = 0
DEFAULT_PROVIDERS = "CPUExecutionProvider"
DEFAULT_THREADS = 0  # ONNX Runtime's own choice
DEFAULT_SPIN_WAIT = False

RW = GObject.ParamFlags.READWRITE
_ERROR_CODES = {
    "not-found": Gst.ResourceError.NOT_FOUND,
    "unreadable": Gst.ResourceError.OPEN_READ,
    "settings": Gst.ResourceError.SETTINGS,
}


class Infer(AttributeProperties, GstBase.BaseTransform):
    __gtype_name__ = "DcuscopeInfer"
    __gstmetadata__ = (
        "Inference", "Filter/Analyzer/Video", "Detects objects in each frame of a batch with an ONNX model",
        "dcuscope",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, BATCH_TEMPLATE_CAPS),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, BATCH_TEMPLATE_CAPS),
    )
    __gproperties__ = PROPERTIES = {
        "model": (str, "Model", "Path of the ONNX detection model", str(DEFAULT_MODEL), RW),
        "decoder": (str, "Decoder", f"Output layout: one of {', '.join(DECODERS)} (auto: recognise the model)",
                    DEFAULT_DECODER, RW),
        "threshold": (float, "Threshold", "Minimum score of a detection", 0.0, 1.0, DEFAULT_THRESHOLD, RW),
        "nms-iou": (float, "NMS IoU", "Overlap above which a box of the same class is dropped",
                    0.0, 1.0, DEFAULT_NMS_IOU, RW),
        "interval": (int, "Interval", "Number of consecutive batches to skip between inferences",
                     0, GLib.MAXINT, DEFAULT_INTERVAL, RW),
        "labels": (str, "Labels", "Path of a labels file, one class name per line (empty: the model's default)",
                   "", RW),
        "providers": (str, "Providers", "Comma-separated ONNX Runtime execution providers, in order of preference",
                      DEFAULT_PROVIDERS, RW),
        "threads": (int, "Threads", "ONNX Runtime intra-op threads (0: its default)", 0, 1024, DEFAULT_THREADS, RW),
        "spin-wait": (bool, "Spin wait", "ONNX Runtime threads spin between batches: a little less latency per "
                      "batch, but they burn CPU time the other stages need", DEFAULT_SPIN_WAIT, RW),
    }
    CHOICES = {"decoder": DECODERS}

    def __init__(self):
        super().__init__()
        self.init_properties()
        self.detector: Detector | None = None
        self.names: list[str] = []
        self.layout: BatchLayout | None = None
        self.batches = 0
        self.found: Counter[str] = Counter()
        """Objects found since the start, per label (``dcuscope run`` says them at the end)."""
        self.inferred_frames = 0
        self.set_in_place(True)

    def _post_error(self, prop: str, text: str, code: Gst.ResourceError, debug: str) -> None:
        text = f'{self.get_name()}: property "{prop}": {text}'
        self.post_message(Gst.Message.new_error(self, GLib.Error.new_literal(Gst.ResourceError.quark(), text, code),
                                                debug))

    def _warn_providers(self, missing: list[str], used: list[str]) -> None:
        text = f"{self.get_name()}: providers {', '.join(missing)} not available here, using {', '.join(used)}"
        Gst.warning(text)
        warning = GLib.Error.new_literal(Gst.ResourceError.quark(), text, Gst.ResourceError.SETTINGS)
        self.post_message(Gst.Message.new_warning(self, warning, ""))

    def do_start(self):
        if self.decoder not in DECODERS:
            self._post_error("decoder", f"{self.decoder!r} is not one of {', '.join(DECODERS)}",
                             Gst.ResourceError.SETTINGS, "")
            return False
        providers, missing = select_providers(self.providers)
        prop = "model"
        try:
            session = open_session(self.model, providers, self.threads, self.spin_wait)
            # A provider this onnxruntime has can still fail to start (no GPU, no cuDNN): ORT
            # then falls back to the next one without an error.
            missing += [p for p in providers if p not in session.get_providers()]
            if missing:
                self._warn_providers(missing, session.get_providers())
            layout = inspect_model(session, self.decoder, self.model)
            prop = "labels"
            self.names = load_labels(self.labels) if self.labels else default_labels(layout)
        except ModelError as exc:
            self._post_error(prop, str(exc), _ERROR_CODES[exc.code], repr(exc.__cause__ or exc))
            return False
        self.detector = Detector(session, layout)
        self.batches = 0
        self.found.clear()
        self.inferred_frames = 0
        return True

    def do_stop(self):
        self.detector = None  # frees the session and its memory
        return True

    def do_set_caps(self, incaps, outcaps):
        self.layout = BatchLayout.from_caps(incaps)
        return True

    def do_transform_ip(self, buf):
        run = self.batches % (self.interval + 1) == 0
        self.batches += 1
        if not run:
            return Gst.FlowReturn.OK
        try:
            with mapped_batch(buf, self.layout) as frames:
                found = self.detector.detect(frames, self.threshold, self.nms_iou)
        except Exception as exc:  # ORT and reshape errors alike: stop the pipeline with a reason
            self._post_error("model", f"inference with {self.model} failed: {exc}", Gst.ResourceError.FAILED,
                             repr(exc))
            return Gst.FlowReturn.ERROR
        detections = self._detections(found)
        write_objects(buf, detections)
        self.found.update(detections.labels)
        self.inferred_frames += len(found)
        return Gst.FlowReturn.OK

    def _detections(self, found: list[Objects]) -> Detections:
        names, n = self.names, len(self.names)
        return Detections.concat([
            Detections(slot=np.full(len(objs.scores), slot, np.int32), cls=objs.classes, score=objs.scores,
                       boxes=objs.boxes, labels=[names[c] if 0 <= c < n else str(c) for c in objs.classes.tolist()])
            for slot, objs in enumerate(found)
        ])


GObject.type_register(Infer)
__gstelementfactory__ = ("infer", Gst.Rank.NONE, Infer)
