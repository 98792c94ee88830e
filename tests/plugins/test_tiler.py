"""The tiler element in real pipelines: appsrc batches -> tiler -> appsink."""

import numpy as np
import pytest

from dcuscope.core.gst import Gst
from dcuscope.plugins import frames, tiler
from dcuscope.plugins.frames import Detections, FrameId

FW, FH = 64, 48  # frame size in the batch


def register() -> None:
    name, rank, cls = tiler.__gstelementfactory__
    if Gst.ElementFactory.find(name) is None:
        Gst.Element.register(None, name, rank, cls.__gtype__)


def make_batch(sources, pts=0, with_objects=True) -> Gst.Buffer:
    """One memory per frame; frame i is filled with (i+1)*40 and has one box."""
    buf = Gst.Buffer.new()
    for i, _ in enumerate(sources):
        pixels = np.full((FH, FW, 3), (i + 1) * 40, np.uint8)
        buf.append_memory(Gst.Buffer.new_wrapped(pixels.tobytes()).get_memory(0))
    buf.pts, buf.duration = pts, Gst.SECOND // 10
    frames.write_frames(buf, [FrameId(s, 7, 1000 + s) for s in sources])
    if with_objects:
        n = len(sources)
        frames.write_objects(buf, Detections(
            slot=np.arange(n, dtype=np.int32), cls=np.arange(n, dtype=np.int32) + 1,
            score=np.full(n, 0.75, np.float32), boxes=np.tile(np.array([[8, 12, 40, 36]], np.float32), (n, 1)),
            labels=[f"obj{i}" for i in range(n)],
        ))
    return buf


def run_tiler(batches, props="width=128 height=96", batch_size=4):
    register()
    pipeline = Gst.parse_launch(f"appsrc name=src format=time ! tiler name=t {props} ! appsink name=sink sync=false")
    src, sink = pipeline.get_by_name("src"), pipeline.get_by_name("sink")
    src.set_property("caps", frames.batch_caps(FW, FH, batch_size, (10, 1)))
    assert pipeline.set_state(Gst.State.PLAYING) != Gst.StateChangeReturn.FAILURE
    for b in batches:
        src.emit("push-buffer", b)
    src.emit("end-of-stream")
    samples = []
    try:
        while True:
            sample = sink.emit("try-pull-sample", 5 * Gst.SECOND)
            if sample is None:
                break
            samples.append(sample)
        msg = pipeline.get_bus().pop_filtered(Gst.MessageType.ERROR)
        assert msg is None, msg.parse_error()
    finally:
        pipeline.set_state(Gst.State.NULL)
    return samples


def pixels(sample) -> np.ndarray:
    buf = sample.get_buffer()
    s = sample.get_caps().get_structure(0)
    w, h = s.get_value("width"), s.get_value("height")
    return np.frombuffer(buf.extract_dup(0, buf.get_size()), np.uint8).reshape(h, w, 3)


def test_four_frame_batch_becomes_2x2_collage_with_boxes_in_tiles():
    (sample,) = run_tiler([make_batch([0, 1, 2, 3])])
    s = sample.get_caps().get_structure(0)
    assert (s.get_value("format"), s.get_value("width"), s.get_value("height")) == ("RGB", 128, 96)
    assert s.get_value("framerate") == Gst.Fraction(10, 1)
    img = pixels(sample)
    assert (img[:48, :64] == 40).all() and (img[:48, 64:] == 80).all()
    assert (img[48:, :64] == 120).all() and (img[48:, 64:] == 160).all()
    buf = sample.get_buffer()
    assert [f.source for f in frames.read_frames(buf)] == [0, 1, 2, 3]
    assert [f.origin_ns for f in frames.read_frames(buf)] == [1000, 1001, 1002, 1003]
    dets = frames.read_objects(buf)
    # 64x48 frames into 64x48 tiles: boxes only move by the tile's corner.
    np.testing.assert_allclose(dets.boxes, [[8, 12, 40, 36], [72, 12, 104, 36], [8, 60, 40, 84], [72, 60, 104, 84]])
    assert dets.cls.tolist() == [1, 2, 3, 4] and dets.labels == ["obj0", "obj1", "obj2", "obj3"]
    assert buf.pts == 0


def test_tile_follows_source_id_and_missing_source_leaves_a_black_tile():
    (sample,) = run_tiler([make_batch([3, 0, 1])], props="width=256 height=192")
    img = pixels(sample)
    assert (img[96:, 128:] == 40).all()  # slot 0 is source 3: bottom-right, scaled 2x
    assert (img[:96, :128] == 80).all()
    assert (img[:96, 128:] == 120).all()
    assert (img[96:, :128] == 0).all()  # source 2 absent
    dets = frames.read_objects(sample.get_buffer())
    np.testing.assert_allclose(dets.boxes[0], [128 + 16, 96 + 24, 128 + 80, 96 + 72])


def test_sources_outside_the_grid_are_left_out_with_their_boxes():
    (sample,) = run_tiler([make_batch([0, 5])], props="rows=1 columns=2 width=128 height=48", batch_size=2)
    img = pixels(sample)
    assert (img[:, :64] == 40).all() and (img[:, 64:] == 0).all()
    dets = frames.read_objects(sample.get_buffer())
    assert len(dets) == 1 and dets.labels == ["obj0"]


def test_stream_of_batches_keeps_timestamps_and_holds_missing_cameras():
    batches = [make_batch([0, 1, 2, 3], pts=i * Gst.SECOND // 10) for i in range(3)]
    batches.append(make_batch([1], pts=3 * Gst.SECOND // 10, with_objects=False))
    samples = run_tiler(batches)
    assert [s.get_buffer().pts for s in samples] == [i * Gst.SECOND // 10 for i in range(4)]
    last = pixels(samples[-1])
    assert (last[:48, 64:] == 40).all()
    # Sources 0, 2, 3 are missing from the last batch: their tiles keep their last picture
    # and their boxes (a video wall does not flash black when a camera is late).
    before = pixels(samples[-2])
    assert (last[:48, :64] == before[:48, :64]).all() and (last[48:] == before[48:]).all()
    assert (before[:48, :64] != 0).any()
    held = frames.read_objects(samples[-1].get_buffer())
    assert len(held) == 3 and sorted(held.labels) == sorted(
        l for l in frames.read_objects(samples[-2].get_buffer()).labels if l != "obj1")


def test_changing_the_grid_while_playing_renegotiates():
    register()
    pipeline = Gst.parse_launch("appsrc name=src format=time ! tiler name=t width=128 height=96 ! appsink name=sink")
    src, sink = pipeline.get_by_name("src"), pipeline.get_by_name("sink")
    src.set_property("caps", frames.batch_caps(FW, FH, 4, (10, 1)))
    try:
        pipeline.set_state(Gst.State.PLAYING)
        src.emit("push-buffer", make_batch([0, 1, 2, 3]))
        assert sink.emit("try-pull-sample", 5 * Gst.SECOND).get_caps().get_structure(0).get_value("width") == 128
        pipeline.get_by_name("t").set_property("columns", 4)
        pipeline.get_by_name("t").set_property("width", 256)
        src.emit("push-buffer", make_batch([0, 1, 2, 3], pts=Gst.SECOND // 10))
        sample = sink.emit("try-pull-sample", 5 * Gst.SECOND)
    finally:
        pipeline.set_state(Gst.State.NULL)
    assert sample.get_caps().get_structure(0).get_value("width") == 256
    assert pixels(sample)[50, ::64, 0].tolist() == [40, 80, 120, 160]  # one row of four tiles


def test_a_frame_of_the_wrong_size_is_a_stream_error():
    register()
    bad = Gst.Buffer.new()
    bad.append_memory(Gst.Buffer.new_wrapped(bytes(FW * FH * 3 - 3)).get_memory(0))
    pipeline = Gst.parse_launch("appsrc name=src format=time ! tiler name=t ! fakesink")
    src = pipeline.get_by_name("src")
    src.set_property("caps", frames.batch_caps(FW, FH, 1, None))
    try:
        pipeline.set_state(Gst.State.PLAYING)
        src.emit("push-buffer", bad)
        msg = pipeline.get_bus().timed_pop_filtered(5 * Gst.SECOND, Gst.MessageType.ERROR)
    finally:
        pipeline.set_state(Gst.State.NULL)
    assert msg is not None and "t: cannot tile a batch of 1 frames of 64x48" in msg.parse_error()[0].message


def test_unknown_property_is_an_error():
    register()
    with pytest.raises(Exception, match="nonexistent"):
        Gst.parse_launch("fakesrc ! tiler nonexistent=1 ! fakesink")
    with pytest.raises(TypeError):
        Gst.ElementFactory.make("tiler").set_property("nonexistent", 1)
