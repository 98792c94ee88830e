"""tiler: a batch of frames -> one rows x columns collage (nvmultistreamtiler).

Each frame goes to the tile of its source id, so a camera keeps its place when another one is
missing from a batch; frames whose source id does not fit the grid are left out and empty tiles
are black. Detections follow their frame into collage pixels; frame identities are kept.

    gst-launch-1.0 videotestsrc num-buffers=5 ! framestamp source-id=0 ! m.sink_0 \
        videotestsrc num-buffers=5 pattern=ball ! framestamp source-id=1 ! m.sink_1 \
        mux name=m batch-size=2 width=640 height=360 ! tiler width=1280 height=360 ! fakesink
"""

import numpy as np

from dcuscope.core.gst import GLib, GObject, Gst, GstBase, GstVideo
from dcuscope.plugins.frames import (
    BATCH_TEMPLATE_CAPS, OBJECTS_CAPS, BatchLayout, Detections, mapped_batch, mapped_video,
    read_frames, read_objects, write_objects,
)
from dcuscope.plugins.properties import AttributeProperties
from dcuscope.plugins.tiling import compose, grid_shape, map_boxes, tile_rects, tiles_for_slots

DEFAULT_ROWS = 0
DEFAULT_COLUMNS = 0
DEFAULT_WIDTH = 1280
DEFAULT_HEIGHT = 720
MAX_SIZE = 32768

SRC_CAPS = Gst.Caps.from_string(
    f"video/x-raw, format=(string)RGB, width=(int)[1,{MAX_SIZE}], height=(int)[1,{MAX_SIZE}]"
)


class Tiler(AttributeProperties, GstBase.BaseTransform):
    __gtype_name__ = "DcuscopeTiler"
    __gstmetadata__ = (
        "Multi-stream tiler", "Filter/Video/Compositor",
        "Composes a batch of frames into one rows x columns collage, tile = source id", "dcuscope",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, BATCH_TEMPLATE_CAPS),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, SRC_CAPS),
    )
    __gproperties__ = PROPERTIES = {
        "rows": (int, "Rows", "Rows of the grid (0 = automatic from the batch size)",
                 0, 1024, DEFAULT_ROWS, GObject.ParamFlags.READWRITE),
        "columns": (int, "Columns", "Columns of the grid (0 = automatic from the batch size)",
                    0, 1024, DEFAULT_COLUMNS, GObject.ParamFlags.READWRITE),
        "width": (int, "Width", "Width of the collage in pixels",
                  1, MAX_SIZE, DEFAULT_WIDTH, GObject.ParamFlags.READWRITE),
        "height": (int, "Height", "Height of the collage in pixels",
                   1, MAX_SIZE, DEFAULT_HEIGHT, GObject.ParamFlags.READWRITE),
    }

    def __init__(self):
        super().__init__()
        self.init_properties()
        self.layout = None
        self.out_info = None
        self.rects = None

    def property_changed(self, name):
        # A new grid or size needs new caps downstream; takes effect on the next buffer.
        self.reconfigure_src()

    def do_transform_caps(self, direction, caps, filter_):
        if direction == Gst.PadDirection.SRC:
            result = BATCH_TEMPLATE_CAPS.copy()
        else:
            result = Gst.Caps.new_empty()
            for i in range(caps.get_size()):
                s = caps[i]  # a copy: PyGObject never hands out the caps' own
                out = Gst.Structure.new_empty("video/x-raw")
                out.set_value("format", "RGB")
                out.set_value("width", self.width)
                out.set_value("height", self.height)
                if s.has_field("framerate"):
                    out.set_value("framerate", s.get_value("framerate"))
                result.append_structure(out)
        if filter_ is not None:
            result = filter_.intersect_full(result, Gst.CapsIntersectMode.FIRST)
        return result

    def do_set_caps(self, incaps, outcaps):
        self.layout = BatchLayout.from_caps(incaps)
        self.out_info = GstVideo.VideoInfo.new_from_caps(outcaps)
        rows, columns = grid_shape(self.layout.batch_size, self.rows, self.columns)
        self.rects = tile_rects(rows, columns, self.out_info.width, self.out_info.height)
        # A camera missing from a batch (slower rate, late, dead) keeps its last picture and
        # boxes in its tile, as a video wall would, instead of flashing black.
        self.canvas = np.zeros((self.out_info.height, self.out_info.width, 3), np.uint8)
        self.held = [Detections() for _ in self.rects]
        return True

    def do_transform_size(self, direction, caps, size, othercaps):
        # A batch's size depends on how many frames it holds; the collage's never does.
        return True, self.out_info.size

    def do_transform(self, inbuf, outbuf):
        n = inbuf.n_memory()
        tiles = tiles_for_slots([f.source for f in read_frames(inbuf)], n, len(self.rects))
        try:
            with mapped_batch(inbuf, self.layout) as frames, mapped_video(outbuf, self.out_info, write=True) as out:
                filled = compose(frames, tiles, self.rects, self.canvas, blank_empty=False)
                np.copyto(out, self.canvas)
        except (ValueError, RuntimeError) as exc:  # e.g. a frame whose size is not the caps'
            text = (f"{self.get_name()}: cannot tile a batch of {n} frames of "
                    f"{self.layout.width}x{self.layout.height}: {exc}")
            err = GLib.Error.new_literal(Gst.StreamError.quark(), text, Gst.StreamError.FORMAT)
            self.post_message(Gst.Message.new_error(self, err, text))
            return Gst.FlowReturn.ERROR
        self._move_detections(outbuf, read_objects(inbuf), tiles, filled)
        return Gst.FlowReturn.OK

    def _move_detections(self, outbuf: Gst.Buffer, dets: Detections, tiles, filled) -> None:
        # BaseTransform already copied the batch's metas (identity and detections in frame
        # pixels); swap the detections for their collage-pixel version, plus the held boxes
        # of the tiles this batch did not refresh.
        stale = outbuf.get_reference_timestamp_meta(OBJECTS_CAPS)
        if stale is not None:
            outbuf.remove_meta(stale.parent)
        boxes, keep = map_boxes(dets.boxes, dets.slot, tiles, self.rects, self.layout.width, self.layout.height)
        fresh = dets.subset(keep)
        fresh.boxes = boxes
        fresh_tiles = tiles[fresh.slot] if len(fresh) else np.zeros(0, int)
        for tile in np.flatnonzero(filled):
            self.held[tile] = fresh.subset(fresh_tiles == tile)
        combined = Detections.concat([fresh, *(self.held[t] for t in np.flatnonzero(~filled))])
        if len(combined):
            write_objects(outbuf, combined)


GObject.type_register(Tiler)
__gstelementfactory__ = ("tiler", Gst.Rank.NONE, Tiler)
