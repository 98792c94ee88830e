"""convert: colour conversion and scaling of raw video (nvvideoconvert).

Converts between RGB, BGR, RGBA, BGRA, RGBx, BGRx, I420, NV12 and GRAY8 and scales to
``width`` x ``height`` with OpenCV; passes buffers through untouched when nothing changes.
YUV output is BT.601 limited range and says so in its caps (``colorimetry=bt601``); YUV input
may be any matrix (see ``plugins/colorspace.py``). Detections are scaled with the frame.

    gst-launch-1.0 videotestsrc num-buffers=5 ! video/x-raw,format=RGB,width=640,height=480 \
        ! convert format=NV12 width=320 height=240 ! fakesink
"""

from contextlib import contextmanager
from typing import Iterator

import numpy as np

from dcuscope.core.gst import GLib, GObject, Gst, GstBase, GstVideo
from dcuscope.plugins.colorspace import BT601, FORMATS, YUV420, Converter, Image, YuvMatrix, image_from_memory
from dcuscope.plugins.frames import OBJECTS_CAPS, Detections, read_objects, write_objects
from dcuscope.plugins.properties import AttributeProperties

DEFAULT_FORMAT = "RGBA"
DEFAULT_WIDTH = 0  # keep the input's
DEFAULT_HEIGHT = 0
MAX_SIZE = 32768
OUTPUT_COLORIMETRY = "bt601"  # what colorspace.Converter writes for I420/NV12

CAPS = Gst.Caps.from_string(
    f"video/x-raw, format=(string){{ {', '.join(FORMATS)} }}, "
    f"width=(int)[1,{MAX_SIZE}], height=(int)[1,{MAX_SIZE}]"
)
_SIZE_FIELDS = ("width", "height")
_COLOUR_FIELDS = ("colorimetry", "chroma-site")


def check_format(value: str) -> str:
    """``value`` if it is a format the element converts to; a ValueError naming the choices otherwise."""
    if value not in FORMATS:
        raise ValueError(f"unknown format {value!r}: use one of {', '.join(FORMATS)}")
    return value


def yuv_matrix(info: GstVideo.VideoInfo) -> YuvMatrix:
    """The colour matrix and range of a YUV stream, as negotiated in its caps."""
    ok, kr, kb = GstVideo.video_color_matrix_get_Kr_Kb(info.colorimetry.matrix)
    full = info.colorimetry.range == getattr(GstVideo.VideoColorRange, "0_255")
    return YuvMatrix(kr, kb, full) if ok else YuvMatrix(BT601.kr, BT601.kb, full)


@contextmanager
def mapped_image(buf: Gst.Buffer, info: GstVideo.VideoInfo, write: bool = False) -> Iterator[Image]:
    """Map a raw video buffer as plane views (zero-copy), honouring a GstVideoMeta's layout."""
    flags = Gst.MapFlags.READ | (Gst.MapFlags.WRITE if write else 0)
    meta = GstVideo.buffer_get_video_meta(buf)
    offsets, strides = (meta.offset, meta.stride) if meta is not None else (info.offset, info.stride)
    ok, mapinfo = buf.map(flags)
    if not ok:
        raise RuntimeError("cannot map video buffer")
    image = None
    try:
        data = np.frombuffer(mapinfo.data, np.uint8)
        image = image_from_memory(data, info.finfo.name, info.width, info.height, offsets, strides)
        yield image
    finally:
        del image
        buf.unmap(mapinfo)


class Convert(AttributeProperties, GstBase.BaseTransform):
    __gtype_name__ = "DcuscopeConvert"
    __gstmetadata__ = (
        "Video convert", "Filter/Converter/Video/Scaler",
        "Converts between RGB, BGR, RGBA, BGRA, RGBx, BGRx, I420, NV12, GRAY8 and scales (OpenCV)",
        "dcuscope",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, CAPS),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, CAPS),
    )
    __gproperties__ = PROPERTIES = {
        "format": (str, "Format", f"Output format: one of {', '.join(FORMATS)}",
                   DEFAULT_FORMAT, GObject.ParamFlags.READWRITE),
        "width": (int, "Width", "Output width in pixels (0 = the input's)",
                  0, MAX_SIZE, DEFAULT_WIDTH, GObject.ParamFlags.READWRITE),
        "height": (int, "Height", "Output height in pixels (0 = the input's)",
                   0, MAX_SIZE, DEFAULT_HEIGHT, GObject.ParamFlags.READWRITE),
    }
    CHOICES = {"format": FORMATS}

    def __init__(self):
        super().__init__()
        self.init_properties()
        self.in_info = self.out_info = None
        self.converter = None

    def property_changed(self, name):
        self.reconfigure_src()

    def do_start(self):
        try:
            check_format(self.format)
        except ValueError as exc:
            self._error(Gst.LibraryError, Gst.LibraryError.SETTINGS, f"{self.get_name()}: {exc}")
            return False
        return True

    def _error(self, domain, code, text: str) -> None:
        """Post an ERROR message: the application stops the pipeline and shows ``text``."""
        err = GLib.Error.new_literal(domain.quark(), text, code)
        self.post_message(Gst.Message.new_error(self, err, text))

    def do_transform_caps(self, direction, caps, filter_):
        result = Gst.Caps.new_empty()
        for i in range(caps.get_size()):
            s = caps[i]  # a copy: PyGObject never hands out the caps' own
            if direction == Gst.PadDirection.SINK:
                self._output_structure(s)
            else:
                s.set_value("format", Gst.ValueList(list(FORMATS)))
                for name in _COLOUR_FIELDS:
                    s.remove_field(name)
                for name, value in zip(_SIZE_FIELDS, (self.width, self.height)):
                    if value:
                        s.set_value(name, Gst.IntRange(range(1, MAX_SIZE + 1)))
            result.append_structure(s)
        if filter_ is not None:
            result = filter_.intersect_full(result, Gst.CapsIntersectMode.FIRST)
        return result

    def _output_structure(self, s: Gst.Structure) -> None:
        """Turn input caps ``s`` into the output caps, in place."""
        in_fmt = s.get_value("format") if s.has_field("format") else None
        out_fmt = self.format if self.format in FORMATS else DEFAULT_FORMAT
        s.set_value("format", out_fmt)
        for name, value in zip(_SIZE_FIELDS, (self.width, self.height)):
            if value:
                s.set_value(name, value)
        # Same format (or I420 <-> NV12, a plane shuffle): the colours are untouched, keep
        # their description; otherwise say what the new data is.
        same_family = in_fmt == out_fmt or (in_fmt in YUV420 and out_fmt in YUV420)
        if not same_family:
            for name in _COLOUR_FIELDS:
                s.remove_field(name)
            if out_fmt in YUV420:
                s.set_value("colorimetry", OUTPUT_COLORIMETRY)

    def do_set_caps(self, incaps, outcaps):
        self.in_info = GstVideo.VideoInfo.new_from_caps(incaps)
        self.out_info = GstVideo.VideoInfo.new_from_caps(outcaps)
        passthrough = incaps.is_equal(outcaps)
        self.set_passthrough(passthrough)
        if passthrough:
            self.converter = None
            return True
        in_fmt, out_fmt = self.in_info.finfo.name, self.out_info.finfo.name
        matrix = yuv_matrix(self.in_info) if in_fmt in YUV420 else BT601
        try:
            self.converter = Converter(
                in_fmt, (self.in_info.width, self.in_info.height),
                out_fmt, (self.out_info.width, self.out_info.height), matrix,
            )
        except ValueError as exc:
            self._error(Gst.CoreError, Gst.CoreError.NEGOTIATION, f"{self.get_name()}: {exc}")
            return False
        return True

    def do_transform_size(self, direction, caps, size, othercaps):
        return True, self.out_info.size

    def do_transform(self, inbuf, outbuf):
        try:
            with mapped_image(inbuf, self.in_info) as src, mapped_image(outbuf, self.out_info, write=True) as dst:
                self.converter(src, dst)
        except (ValueError, RuntimeError, TypeError) as exc:  # e.g. a buffer smaller than its caps say
            self._error(Gst.StreamError, Gst.StreamError.FORMAT,
                        f"{self.get_name()}: cannot convert a buffer of {inbuf.get_size()} bytes as "
                        f"{self.in_info.finfo.name} {self.in_info.width}x{self.in_info.height}: {exc}")
            return Gst.FlowReturn.ERROR
        if (self.in_info.width, self.in_info.height) != (self.out_info.width, self.out_info.height):
            self._scale_detections(outbuf)
        return Gst.FlowReturn.OK

    def _scale_detections(self, outbuf: Gst.Buffer) -> None:
        # BaseTransform copied the input's metas; boxes there are in input pixels.
        dets = read_objects(outbuf)
        if not len(dets):
            return
        outbuf.remove_meta(outbuf.get_reference_timestamp_meta(OBJECTS_CAPS).parent)
        scale = np.array([self.out_info.width / self.in_info.width, self.out_info.height / self.in_info.height] * 2,
                         np.float32)
        write_objects(outbuf, Detections(dets.slot, dets.cls, dets.score, dets.boxes * scale, dets.labels))


GObject.type_register(Convert)
__gstelementfactory__ = ("convert", Gst.Rank.NONE, Convert)
