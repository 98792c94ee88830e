"""osd: draws detections (boxes, labels with scores) and an optional clock on frames (nvdsosd).

Works in place on packed RGB-family frames; boxes come from the buffer's detections meta and
are in this buffer's pixels (after tiler/convert they already are). Each class has a fixed
colour.

    gst-launch-1.0 videotestsrc num-buffers=5 ! video/x-raw,format=RGB,width=320,height=240 \
        ! convert format=RGBA ! osd display-clock=true ! fakesink
"""

import time

from dcuscope.core.gst import GObject, Gst, GstBase, GstVideo
from dcuscope.plugins.drawing import FORMATS, clock_text, draw_clock, draw_detections
from dcuscope.plugins.frames import mapped_video, read_objects
from dcuscope.plugins.properties import AttributeProperties

DEFAULT_DISPLAY_TEXT = True
DEFAULT_LINE_WIDTH = 2
DEFAULT_DISPLAY_CLOCK = False
DEFAULT_FONT_SCALE = 0.5

CAPS = Gst.Caps.from_string(
    f"video/x-raw, format=(string){{ {', '.join(FORMATS)} }}, width=(int)[1,32768], height=(int)[1,32768]"
)
class Osd(AttributeProperties, GstBase.BaseTransform):
    __gtype_name__ = "DcuscopeOsd"
    __gstmetadata__ = (
        "On-screen display", "Filter/Effect/Video",
        "Draws detection boxes, labels with scores and a wall clock on the frame", "dcuscope",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, CAPS),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, CAPS),
    )
    __gproperties__ = PROPERTIES = {
        "display-text": (bool, "Display text", "Write the label and score above each box",
                         DEFAULT_DISPLAY_TEXT, GObject.ParamFlags.READWRITE),
        "line-width": (int, "Line width", "Width of box outlines in pixels",
                       1, 32, DEFAULT_LINE_WIDTH, GObject.ParamFlags.READWRITE),
        "display-clock": (bool, "Display clock", "Write the wall-clock time (HH:MM:SS.mmm) in the top-left corner",
                          DEFAULT_DISPLAY_CLOCK, GObject.ParamFlags.READWRITE),
        "font-scale": (float, "Font scale", "Size of label and clock text (OpenCV font scale)",
                       0.1, 10.0, DEFAULT_FONT_SCALE, GObject.ParamFlags.READWRITE),
    }

    def __init__(self):
        super().__init__()
        self.init_properties()
        self.info = None
        self.set_in_place(True)

    def do_set_caps(self, incaps, outcaps):
        self.info = GstVideo.VideoInfo.new_from_caps(incaps)
        return True

    def do_transform_ip(self, buf):
        dets = read_objects(buf)
        if not len(dets) and not self.display_clock:
            return Gst.FlowReturn.OK  # nothing to draw: do not even map
        fmt = self.info.finfo.name
        with mapped_video(buf, self.info, write=True) as img:
            if len(dets):
                draw_detections(img, fmt, dets.boxes, dets.cls, dets.score, dets.labels,
                                self.line_width, self.display_text, self.font_scale)
            if self.display_clock:
                draw_clock(img, fmt, clock_text(time.time_ns()), self.font_scale)
        return Gst.FlowReturn.OK


GObject.type_register(Osd)
__gstelementfactory__ = ("osd", Gst.Rank.NONE, Osd)
