"""framestamp: gives every frame its identity where it enters the pipeline.

Attaches (source id, frame number, origin timestamp) to each buffer, in place, so that every
later element and tracepoint can tell which camera frame it is touching. The pipeline builder
puts one at the end of every source; users rarely place it by hand.

    gst-launch-1.0 videotestsrc num-buffers=5 ! framestamp source-id=2 ! fakesink
"""

import time

from dcuscope.core.gst import GObject, Gst, GstBase
from dcuscope.plugins.frames import FrameId, write_frames
from dcuscope.plugins.properties import AttributeProperties

DEFAULT_SOURCE_ID = 0
DEFAULT_CLOCK_ID = 0  # CLOCK_REALTIME, the clock phc2sys disciplines

CAPS = Gst.Caps.new_any()


class FrameStamp(AttributeProperties, GstBase.BaseTransform):
    __gtype_name__ = "DcuscopeFrameStamp"
    __gstmetadata__ = (
        "Frame stamp", "Filter/Video", "Attaches (source, frame number, origin time) to each frame", "dcuscope",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, CAPS),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, CAPS),
    )
    __gproperties__ = PROPERTIES = {
        "source-id": (int, "Source id", "Id of the camera or file this frame comes from",
                      0, 65535, DEFAULT_SOURCE_ID, GObject.ParamFlags.READWRITE),
        "clock-id": (int, "Clock id", "Linux clock for origin timestamps: 0 realtime, 1 monotonic, 11 tai",
                     0, 11, DEFAULT_CLOCK_ID, GObject.ParamFlags.READWRITE),
    }

    def __init__(self):
        super().__init__()
        self.init_properties()
        self.count = 0
        self.set_in_place(True)

    def do_start(self):
        self.count = 0
        return True

    def do_transform_ip(self, buf):
        write_frames(buf, [FrameId(self.source_id, self.count, time.clock_gettime_ns(self.clock_id))])
        self.count += 1
        return Gst.FlowReturn.OK


GObject.type_register(FrameStamp)
__gstelementfactory__ = ("framestamp", Gst.Rank.NONE, FrameStamp)
