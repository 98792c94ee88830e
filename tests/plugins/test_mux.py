"""mux: rate-aware batching of streams of different sizes and rates; one stream ending early."""

from __future__ import annotations

import time

import numpy as np
import pytest

from dcuscope.core.gst import Gst, GstVideo
from dcuscope.plugins.frames import BatchLayout, mapped_batch, read_frames
from dcuscope.plugins.mux import due_pads
from tests.pipeline.clips import decode_video


def test_due_pads_takes_frames_within_one_period_of_the_earliest():
    assert due_pads([(0, 0), (0, 1)], 40, 4) == [0, 1]
    assert due_pads([(40, 0), (100, 1)], 40, 4) == [0]  # the 10 fps frame is not due yet
    assert due_pads([(120, 0), (100, 1)], 40, 4) == [1, 0]  # earliest first
    assert due_pads([(0, 0), (5, 1), (9, 2)], 40, 2) == [0, 1]  # batch-size limit
    assert due_pads([(0, 0), (999, 1)], 0, 4) == [0, 1]  # no rate known: everything that is there
    assert due_pads([], 40, 4) == []


def run(launch: str) -> list[tuple[int, list[tuple[int, int]], list[float], tuple[int, int]]]:
    from dcuscope import plugins

    plugins.register()
    pipeline = Gst.parse_launch(launch)
    out = []

    def handoff(_sink, buf, pad):
        layout = BatchLayout.from_caps(pad.get_current_caps())
        with mapped_batch(buf, layout) as frames:
            out.append((buf.pts, [(f.source, f.frame) for f in read_frames(buf)],
                        [float(f.mean()) for f in frames], (layout.width, layout.height)))

    pipeline.get_by_name("out").connect("handoff", handoff)
    pipeline.set_state(Gst.State.PLAYING)
    msg = pipeline.get_bus().timed_pop_filtered(20 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    pipeline.set_state(Gst.State.NULL)
    assert msg is not None and msg.type == Gst.MessageType.EOS, msg and msg.parse_error()
    return out


def test_streams_of_different_sizes_and_rates_one_ending_early():
    batches = run(
        "mux name=m width=320 height=240 ! fakesink name=out signal-handoffs=true "
        "videotestsrc num-buffers=10 pattern=white ! video/x-raw,format=RGB,width=320,height=240,framerate=25/1 "
        "! framestamp source-id=0 ! m.sink_0 "
        "videotestsrc num-buffers=3 pattern=black ! video/x-raw,format=RGB,width=641,height=200,framerate=10/1 "
        "! framestamp source-id=1 ! m.sink_1"
    )
    assert all(size == (320, 240) for *_, size in batches)
    # The 25 fps stream is in every batch; the 10 fps one joins when its frame is due (0, 100, 200 ms).
    assert [ids for _, ids, _, _ in batches[:6]] == [
        [(0, 0), (1, 0)], [(0, 1)], [(0, 2), (1, 1)], [(0, 3)], [(0, 4)], [(0, 5), (1, 2)]]
    assert [pts // Gst.MSECOND for pts, *_ in batches[:3]] == [0, 40, 80]
    # After the short stream's EOS the other one goes on to its end, alone.
    assert [ids for _, ids, _, _ in batches[6:]] == [[(0, f)] for f in range(6, 10)]
    # Pixels: white frames stay white; the 641x200 black frames were scaled to 320x240, black.
    means = [m for _, _, ms, _ in batches for m in ms]
    assert max(means) > 250 and min(means) < 5


def test_frames_without_identity_get_one_from_the_pad():
    batches = run(
        "mux name=m batch-size=2 width=64 height=48 ! fakesink name=out signal-handoffs=true "
        "videotestsrc num-buffers=3 ! video/x-raw,format=RGB,width=64,height=48 ! m.sink_0 "
        "videotestsrc num-buffers=3 ! video/x-raw,format=RGB,width=64,height=48 ! m.sink_1"
    )
    assert [ids for _, ids, _, _ in batches] == [[(0, i), (1, i)] for i in range(3)]


def test_a_frame_that_cannot_be_scaled_into_its_batch_slot_is_left_unmapped():
    """The input frame was mapped, then the batch slot failed to map: the input stayed mapped for ever."""
    from dcuscope.plugins.mux import scale_into

    info = GstVideo.VideoInfo.new()
    info.set_format(GstVideo.VideoFormat.RGB, 64, 48)
    frame = Gst.Buffer.new_allocate(None, info.size, None)
    slot = Gst.Allocator.find(None).alloc(32 * 24 * 3, None)
    slot.mini_object.flags |= Gst.MemoryFlags.READONLY  # a slot that cannot be mapped for writing
    unmapped = frame.peek_memory(0).mini_object.lockstate
    with pytest.raises(RuntimeError, match="cannot map"):
        scale_into(frame, info, slot, 32, 24)
    assert frame.peek_memory(0).mini_object.lockstate == unmapped


def test_a_frame_is_scaled_into_its_batch_slot():
    from dcuscope.plugins.mux import scale_into

    info = GstVideo.VideoInfo.new()
    info.set_format(GstVideo.VideoFormat.RGB, 64, 48)
    frame = Gst.Buffer.new_wrapped(np.full((48, 64, 3), 200, np.uint8).tobytes())
    slot = Gst.Allocator.find(None).alloc(32 * 24 * 3, None)
    scale_into(frame, info, slot, 32, 24)
    ok, mapped = slot.map(Gst.MapFlags.READ)
    assert ok and np.all(np.frombuffer(mapped.data, np.uint8) == 200)
    slot.unmap(mapped)


def test_live_cameras_that_push_together_make_full_batches():
    """Two live cameras at 10 fps push each frame a frame period after its running time (its
    capture began then). The aggregator's own next time, its output position, stayed 0: the push
    timeout had always passed, and 80-90 % of the batches went out with one camera alone."""
    camera = "videotestsrc is-live=true num-buffers=20 ! video/x-raw,format=RGB,width=64,height=48,framerate=10/1"
    batches = run(f"mux name=m width=64 height=48 live-source=true ! fakesink name=out signal-handoffs=true "
                  f"{camera} ! framestamp source-id=0 ! m.sink_0 {camera} ! framestamp source-id=1 ! m.sink_1")
    assert sorted(i for _, ids, _, _ in batches for i in ids) == [(s, f) for s in (0, 1) for f in range(20)]
    # every batch has both cameras' frame of one period (the last may be pushed alone at the end)
    full = [ids for _, ids, _, _ in batches if len(ids) == 2]
    assert len(full) >= 19 and all(a[1] == b[1] for a, b in full), batches


def test_a_late_frame_never_stamps_a_batch_at_or_before_the_last_one():
    """Live: the mux pushes on its timeout without a late camera; the late frame, whose running
    time is that of the batch already gone, came out as a second batch with the same PTS, which
    an encoder cannot take (mp4mux: "Could not multiplex stream")."""
    batches = run(
        "mux name=m width=64 height=48 batched-push-timeout=1000 ! fakesink name=out signal-handoffs=true "
        "videotestsrc is-live=true num-buffers=8 ! video/x-raw,format=RGB,width=64,height=48,framerate=10/1 "
        "! framestamp source-id=0 ! m.sink_0 "
        "videotestsrc is-live=true num-buffers=8 ! video/x-raw,format=RGB,width=64,height=48,framerate=10/1 "
        "! identity sleep-time=130000 ! framestamp source-id=1 ! m.sink_1"
    )
    assert sorted(i for _, ids, _, _ in batches for i in ids) == [(s, f) for s in (0, 1) for f in range(8)]
    assert any(len(ids) == 1 for _, ids, _, _ in batches)  # the delay made the mux push without camera 1
    stamps = [pts for pts, *_ in batches]
    assert all(a < b for a, b in zip(stamps, stamps[1:])), stamps


def test_every_batch_of_a_late_camera_keeps_its_own_frame_in_an_mp4(tmp_path):
    """A late camera's lone batches, stamped just after the batch they missed, were merged with it
    by the container (1 ns apart): 34 of 40 collages decoded. Every batch must reach the file."""
    from dcuscope import plugins

    plugins.register()
    path = tmp_path / "late.mp4"
    camera = "videotestsrc is-live=true num-buffers=10 ! video/x-raw,format=RGB,width=64,height=48,framerate=10/1"
    pipeline = Gst.parse_launch(
        "mux name=m width=64 height=48 batched-push-timeout=1000 ! tiler rows=1 columns=2 width=128 height=48 "
        f'! convert format=RGBA ! videoconvert ! x264enc speed-preset=ultrafast ! mp4mux ! filesink location="{path}" '
        f"{camera} ! framestamp source-id=0 ! m.sink_0 {camera} ! identity sleep-time=130000 ! framestamp source-id=1 ! m.sink_1")
    batches = []
    pipeline.get_by_name("m").get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER,
                                                               lambda pad, info: batches.append(1) or Gst.PadProbeReturn.OK)
    pipeline.set_state(Gst.State.PLAYING)
    msg = pipeline.get_bus().timed_pop_filtered(30 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    pipeline.set_state(Gst.State.NULL)
    assert msg is not None and msg.type == Gst.MessageType.EOS, msg and msg.parse_error()
    assert len(batches) > 10  # the delay made the mux push without camera 1
    assert len(decode_video(path)) == len(batches)


LATE_LIMIT_MS = 100
LATE_FRAMES = 80  # per camera: 1.6 s at 50 frames/s, twice what the slow stage can take


def run_behind(max_latency: int) -> tuple[list[tuple[int, list]], list[Gst.Structure], int]:
    """Two live 50 fps cameras, each queued without bound after its framestamp, into a mux whose
    batches a 40 ms stage takes: the pipeline cannot keep up. Returns the batches as the sink got
    them (realtime ns on arrival, frame ids), the drop messages, and how many frames were stamped."""
    from dcuscope import plugins

    plugins.register()
    camera = ("videotestsrc is-live=true num-buffers={n} ! video/x-raw,format=RGB,width=64,height=48,framerate=50/1 "
              "! framestamp source-id={i} ! queue max-size-buffers=0 max-size-bytes=0 max-size-time=0 ! m.sink_{i} ")
    pipeline = Gst.parse_launch(
        f"mux name=m width=64 height=48 live-source=true max-latency={max_latency} "
        "! identity sleep-time=40000 ! fakesink name=out sync=false "
        + "".join(camera.format(n=LATE_FRAMES, i=i) for i in (0, 1)))
    arrivals = []

    def arrived(_pad, info):
        arrivals.append((time.clock_gettime_ns(time.CLOCK_REALTIME), read_frames(info.get_buffer())))
        return Gst.PadProbeReturn.OK

    pipeline.get_by_name("out").get_static_pad("sink").add_probe(Gst.PadProbeType.BUFFER, arrived)
    pipeline.set_state(Gst.State.PLAYING)
    drops = []
    while True:
        msg = pipeline.get_bus().timed_pop_filtered(
            60 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR | Gst.MessageType.ELEMENT)
        if msg is None or msg.type != Gst.MessageType.ELEMENT:
            break
        if msg.get_structure().get_name() == "dcuscope-drop":
            assert msg.src == pipeline.get_by_name("m")
            drops.append(msg.get_structure())
    pipeline.set_state(Gst.State.NULL)
    assert msg is not None and msg.type == Gst.MessageType.EOS, msg and msg.parse_error()
    return arrivals, drops, 2 * LATE_FRAMES


def late_by(arrivals) -> list[int]:
    """For each batch after the first: how much older than the previous batch's arrival its
    oldest frame is. The mux takes a batch only after it has pushed the previous one (its push
    returns once the sink has it), so with max-latency this never exceeds the limit."""
    return [prev - min(f.origin_ns for f in ids) for (prev, _), (_, ids) in zip(arrivals, arrivals[1:])]


def test_max_latency_drops_late_frames_and_keeps_the_delay_bounded():
    arrivals, drops, stamped = run_behind(LATE_LIMIT_MS)
    limit = LATE_LIMIT_MS * 1_000_000
    delivered = [(f.source, f.frame) for _, ids in arrivals for f in ids]
    dropped = [(d.get_value("source"), d.get_value("frame")) for d in drops]
    assert drops and all(d.get_value("reason") == "late" and d.get_value("age-ns") > limit for d in drops)
    # Every frame is accounted for: delivered or dropped, never both, never lost.
    assert sorted(delivered + dropped) == [(s, f) for s in (0, 1) for f in range(LATE_FRAMES)]
    assert len(delivered) + len(dropped) == stamped
    assert max(late_by(arrivals)) <= limit
    # So a frame's delay at the sink is at most the limit plus one batch's trip (measured here).
    cycles = [b - a for (a, _), (b, _) in zip(arrivals, arrivals[1:])]
    delays = [[t - f.origin_ns for f in ids] for t, ids in arrivals[1:]]
    assert all(max(d) <= limit + c for d, c in zip(delays, cycles))


def test_without_max_latency_every_frame_is_batched_and_the_delay_grows():
    arrivals, drops, stamped = run_behind(0)
    assert drops == [] and sum(len(ids) for _, ids in arrivals) == stamped
    late = late_by(arrivals)
    assert max(late) > LATE_LIMIT_MS * 1_000_000  # what max-latency prevents does happen here
    quarter = len(late) // 4
    assert np.mean(late[-quarter:]) > np.mean(late[:quarter]) + LATE_LIMIT_MS * 1_000_000
