"""The tracer on real pipelines: stages, one event per frame per tracepoint, accuracy, batches,
bins, drops, clocks, and the shipping thread."""

import time

import numpy as np
import pytest

from dcuscope.core.clocks import CLOCKS
from dcuscope.core.errors import PipelineError
from dcuscope.core.gst import Gst
from dcuscope.plugins.frames import FrameId, write_frames
from dcuscope.probes.capture import native, tracer as tracer_mod
from dcuscope.probes.capture.ring import PythonRing
from dcuscope.probes.capture.shipper import Shipper
from dcuscope.probes.capture.tracer import attach
from dcuscope.protocol.events import ENTER, EVENT_DTYPE, EXIT, FACT, FACT_THREAD, ORIGIN, READY, TraceHeader
from tests.probes.capture import sleeper

BACKENDS = ["native", "python"]
SMALL = "video/x-raw,width=32,height=24,framerate=1000/1"
MAIN = f"videotestsrc num-buffers=20 ! {SMALL} ! framestamp name=stamp source-id=3 ! identity name=a ! " \
       "queue name=q ! fakesink name=sink"
# (stage, point) a frame passes in MAIN, in order
MAIN_PATH = [(0, ORIGIN), (1, ENTER), (1, EXIT), (2, ENTER), (2, EXIT), (3, ENTER)]


@pytest.fixture(scope="module", autouse=True)
def framestamp_registered():
    from dcuscope.plugins import framestamp

    name, rank, cls = framestamp.__gstelementfactory__
    if Gst.ElementFactory.find(name) is None:
        Gst.Element.register(None, name, rank, cls.__gtype__)
    sleeper.register()


def run(pipe, timeout_s=20):
    pipe.set_state(Gst.State.PLAYING)
    msg = pipe.get_bus().timed_pop_filtered(timeout_s * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    pipe.set_state(Gst.State.NULL)
    assert msg is not None, "pipeline did not finish"
    assert msg.type == Gst.MessageType.EOS, msg.parse_error()


def traced_run(description, backend="native", **kwargs):
    pipe = Gst.parse_launch(description)
    tracer = attach(pipe, "node-a", backend=backend, **kwargs)
    run(pipe)
    events = tracer.drain()
    tracer.detach()
    return tracer, events


def keys(events):
    """(stage, point, source, frame) of the origin, enter and exit events (not ready, facts)."""
    events = events[events["point"] <= EXIT]
    return sorted(zip(events["stage"].tolist(), events["point"].tolist(), events["source"].tolist(),
                      events["frame"].tolist()))


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_event_per_frame_per_tracepoint_in_pipeline_order(backend):
    tracer, ev = traced_run(MAIN, backend)
    assert tracer.backend == backend
    h = tracer.header
    assert (h.node, h.clock, h.stages, h.sources) == ("node-a", "realtime", ["stamp", "a", "q", "sink"], {3: "videotestsrc"})
    assert h.versions["probes"] == backend
    assert keys(ev) == sorted((st, p, 3, f) for st, p in MAIN_PATH for f in range(20))
    assert tracer.stats().dropped == 0 and tracer.stats().unidentified == 0
    for f in range(20):
        mine = ev[(ev["frame"] == f) & (ev["point"] <= EXIT)]
        order = [MAIN_PATH.index((s, p)) for s, p in zip(mine["stage"].tolist(), mine["point"].tolist())]
        ts_along_path = mine["ts"][np.argsort(order)]
        assert (np.diff(ts_along_path) >= 0).all(), f"frame {f}: timestamps go back along the pipeline"
    assert (ev["ts"] >= h.started_ns).all()


def test_native_exits_have_one_ready_point_each_and_thread_facts_tell_the_threads_apart():
    tracer, ev = traced_run(MAIN, "native")
    a, q = tracer.header.stages.index("a"), tracer.header.stages.index("q")

    def at(stage, point):
        """ts by frame of one tracepoint; each frame once."""
        here = ev[(ev["stage"] == stage) & (ev["point"] == point)]
        assert (here["source"] == 3).all() and sorted(here["frame"].tolist()) == list(range(20)), (stage, point)
        return here["ts"][np.argsort(here["frame"])]

    for stage in (a, q):
        enter, ready, exit_ = at(stage, ENTER), at(stage, READY), at(stage, EXIT)
        assert ((enter <= ready) & (ready <= exit_)).all(), stage
        assert (ev["code"][(ev["stage"] == stage) & (ev["point"] == READY)] == 1).all()  # one frame per buffer
    # identity works in the thread that brings the frame: nothing to wait for.
    assert (at(a, READY) == at(a, ENTER)).all()
    assert set(ev["stage"][ev["point"] == READY].tolist()) == {a, q}  # exits only (not origin, not sink)
    facts = ev[(ev["point"] == FACT) & (ev["code"] == FACT_THREAD)]
    thread = dict(zip(facts["stage"].tolist(), facts["frame"].tolist()))
    assert len(facts) == 2 and set(thread) == {a, q}  # told once: neither stage's pushing thread changed
    assert thread[a] != thread[q] and min(thread.values()) >= 1  # the queue pushes from its own thread


def test_both_backends_record_the_same_events():
    _, a = traced_run(MAIN, "native")
    _, b = traced_run(MAIN, "python")
    assert keys(a) == keys(b)


def sleeping_stage_excess_ms(backend):
    """Per frame, the measured delay of a stage that sleeps 20 ms minus the time it really slept
    (``tests.probes.capture.sleeper``: a late wake-up on a loaded machine is in both)."""
    pipe = Gst.parse_launch(f"videotestsrc num-buffers=20 ! {SMALL} ! framestamp ! "
                            "testsleeper name=slow sleep-us=20000 ! fakesink")
    tracer = attach(pipe, "node-a", backend=backend)
    run(pipe)
    ev = tracer.drain()
    tracer.detach()
    slept = sleeper.slept_per_frame(pipe.get_by_name("slow").records)
    slow = tracer.header.stages.index("slow")
    enter = ev[(ev["stage"] == slow) & (ev["point"] == ENTER)]
    exit_ = ev[(ev["stage"] == slow) & (ev["point"] == EXIT)]
    assert sorted(enter["frame"].tolist()) == sorted(exit_["frame"].tolist()) == list(range(20))
    enter, exit_ = enter[np.argsort(enter["frame"])], exit_[np.argsort(exit_["frame"])]
    began, ended = np.array([slept[(int(e["source"]), int(e["frame"]))] for e in enter]).T
    assert ((enter["ts"] <= began) & (ended <= exit_["ts"])).all()  # the sleep lies between the two tracepoints
    assert (ended - began >= 20_000_000).all()
    return ((exit_["ts"] - enter["ts"]) - (ended - began)) / 1e6


@pytest.mark.alone  # its p99 is the slowest of 20 frames: beside five busy workers one preemption fails a run
@pytest.mark.parametrize("backend", BACKENDS)
def test_stage_delay_of_a_sleeping_stage_is_measured_accurately(backend):
    """Within 0.5 ms of the time the stage really slept on average, p99 within 1.5 ms. Being
    preempted between a tracepoint and the sleep is rare but real on a loaded host (it makes the
    stage slower where the element cannot see it), so up to 3 runs of 20 frames, one must meet it."""
    runs = []
    for _ in range(3):
        excess_ms = sleeping_stage_excess_ms(backend)
        runs.append((round(float(excess_ms.mean()), 3), round(float(np.percentile(excess_ms, 99)), 3)))
        if runs[-1][0] <= 0.5 and runs[-1][1] < 1.5:
            return
    pytest.fail(f"(mean, p99) ms over the real sleep, 3 runs: {runs}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_batch_buffer_yields_one_event_per_frame_at_every_tracepoint(backend):
    # No framestamp: frames arrive identified (3 per buffer), every element after appsrc is a stage.
    pipe = Gst.parse_launch("appsrc name=src format=time ! identity name=a ! queue name=q ! fakesink name=sink")
    tracer = attach(pipe, "node-b", backend=backend)
    assert tracer.header.stages == ["a", "q", "sink"]
    assert tracer.header.kinds == {"a": "identity", "q": "queue", "sink": "fakesink"}  # what the UI colours by
    src = pipe.get_by_name("src")
    pipe.set_state(Gst.State.PLAYING)
    for b in range(4):
        buf = Gst.Buffer.new_allocate(None, 3 * 8 * 8 * 3, None)
        write_frames(buf, [FrameId(s, b, 1000 * b + s) for s in (0, 1, 2)])
        src.emit("push-buffer", buf)
    src.emit("end-of-stream")
    msg = pipe.get_bus().timed_pop_filtered(10 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    pipe.set_state(Gst.State.NULL)
    assert msg.type == Gst.MessageType.EOS
    ev = tracer.drain()
    path = [(0, ENTER), (0, EXIT), (1, ENTER), (1, EXIT), (2, ENTER)]
    assert keys(ev) == sorted((st, p, s, b) for st, p in path for s in (0, 1, 2) for b in range(4))
    for (stage, point) in path:
        for b in range(4):
            here = ev[(ev["stage"] == stage) & (ev["point"] == point) & (ev["frame"] == b)]
            assert len(set(here["ts"].tolist())) == 1, "one clock read per buffer"


def test_source_bins_give_their_framestamp_and_sink_bins_are_one_enter_only_stage():
    pipe = Gst.Pipeline.new("bins")
    parts = [
        ("source0", f"videotestsrc num-buffers=5 ! {SMALL} ! framestamp name=src0 source-id=0"),
        ("source1", f"videotestsrc num-buffers=5 pattern=ball ! {SMALL} ! framestamp name=src1 source-id=1"),
        ("qa", "queue"), ("other", "fakesink"), ("a", "identity"), ("sink", "queue ! fakesink"),
    ]
    elements = {}
    for name, desc in parts:
        element = Gst.parse_bin_from_description(desc, True) if name in ("source0", "source1", "sink") \
            else Gst.parse_launch(desc)
        element.set_name(name)
        pipe.add(element)
        elements[name] = element
    for a, b in (("source0", "qa"), ("qa", "other"), ("source1", "a"), ("a", "sink")):
        assert elements[a].link(elements[b])
    tracer = attach(pipe, "node-bins", sources={1: "camera one"})
    run(pipe)
    ev = tracer.drain()
    h = tracer.header
    assert h.stages == ["src0", "src1", "qa", "other", "a", "sink"]
    assert h.sources == {0: "videotestsrc", 1: "camera one"}
    sink = h.stages.index("sink")
    assert set(ev["point"][ev["stage"] == sink].tolist()) == {ENTER}
    assert sorted(ev["frame"][(ev["stage"] == sink)].tolist()) == list(range(5))
    assert sorted(ev["source"][ev["stage"] == h.stages.index("other")].tolist()) == [0] * 5
    assert len(ev[ev["point"] == ORIGIN]) == 10 and set(ev["stage"][ev["point"] == ORIGIN].tolist()) == {0, 1}


def test_source_description_comes_from_a_location_property(tmp_path):
    clip = tmp_path / "clip.raw"
    clip.write_bytes(bytes(32 * 24 * 3 * 3))
    desc = (f"filesrc location={clip} blocksize={32 * 24 * 3} ! rawvideoparse width=32 height=24 format=rgb "
            "! framestamp source-id=4 ! fakesink")
    tracer, ev = traced_run(desc)
    assert tracer.header.sources == {4: str(clip)}
    assert sorted(ev["frame"][ev["point"] == ORIGIN].tolist()) == [0, 1, 2]


def test_pads_added_after_attach_are_traced():
    pipe = Gst.parse_launch(f"videotestsrc num-buffers=5 ! {SMALL} ! framestamp ! tee name=t ! queue ! fakesink")
    tracer = attach(pipe, "node-c")
    before = tracer.tracepoints
    tee = pipe.get_by_name("t")
    extra = Gst.ElementFactory.make("fakesink")
    pipe.add(extra)
    assert tee.request_pad_simple("src_%u").link(extra.get_static_pad("sink")) == Gst.PadLinkReturn.OK
    assert tracer.tracepoints == before + 1
    run(pipe)
    ev = tracer.drain()
    t = tracer.header.stages.index("t")
    assert sorted(ev["frame"][(ev["stage"] == t) & (ev["point"] == EXIT)].tolist()) == sorted(list(range(5)) * 2)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_tiny_ring_drops_and_counts_but_never_blocks(backend):
    started = time.monotonic()
    tracer, ev = traced_run(MAIN, backend, capacity=4)
    assert time.monotonic() - started < 10
    stats = tracer.stats()
    assert stats.written == len(ev)
    assert 1 <= stats.written <= 4 + 1  # Python's bound may be overshot by one buffer per thread
    # Native probes also write a ready record per exit and a thread fact per pushing thread.
    extra = {"native": 2 * 20 + 2, "python": 0}[backend]
    assert stats.written + stats.dropped == len(MAIN_PATH) * 20 + extra
    assert tracer.dropped == stats.dropped


@pytest.mark.parametrize("clock", ["monotonic", "realtime"])
def test_events_are_read_from_the_chosen_clock(clock):
    before = time.clock_gettime_ns(CLOCKS[clock])
    tracer, ev = traced_run(MAIN, clock=clock)
    after = time.clock_gettime_ns(CLOCKS[clock])
    assert tracer.header.clock == clock
    assert ((ev["ts"] >= before) & (ev["ts"] <= after)).all()


def test_detach_removes_every_tracepoint():
    pipe = Gst.parse_launch(MAIN)
    tracer = attach(pipe, "node-d")
    assert tracer.tracepoints == 6  # origin, a in/out, q in/out, sink in
    run(pipe)
    assert len(keys(tracer.drain())) == 120
    tracer.detach()
    assert tracer.tracepoints == 0
    run(pipe)
    assert len(tracer.drain()) == 0


def test_bad_arguments_are_refused():
    pipe = Gst.parse_launch(MAIN)
    with pytest.raises(ValueError, match="clock"):
        attach(pipe, "n", clock="gps")
    with pytest.raises(ValueError, match="backend"):
        attach(pipe, "n", backend="ebpf")
    lonely = Gst.Pipeline.new("lonely")
    lonely.add(Gst.ElementFactory.make("fakesrc"))
    with pytest.raises(PipelineError, match="nothing to trace"):
        attach(lonely, "n")
    with pytest.raises(TypeError, match="Pipeline"):
        attach(Gst.ElementFactory.make("identity"), "n")


def test_auto_falls_back_to_python_probes_when_the_library_is_unavailable(monkeypatch):
    monkeypatch.setattr(native, "_lib", None)
    monkeypatch.setattr(native, "_reason", "no C compiler (cc/gcc) on PATH")
    assert isinstance(tracer_mod.make_ring("auto", 16), PythonRing)
    with pytest.raises(native.BuildError, match="no C compiler"):
        tracer_mod.make_ring("native", 16)


class MemoryExporter:
    """Collects what the shipper hands over, in order."""

    def __init__(self):
        self.calls, self.batches, self.header, self.dropped = [], [], None, None

    def start(self, header: TraceHeader) -> None:
        self.calls.append("start")
        self.header = header

    def write(self, events: np.ndarray) -> None:
        self.calls.append("write")
        assert events.dtype == EVENT_DTYPE
        self.batches.append(events.copy())

    def close(self, dropped: int) -> None:
        self.calls.append("close")
        self.dropped = dropped


class BrokenExporter(MemoryExporter):
    def write(self, events):
        raise OSError("disk full")


@pytest.mark.parametrize("backend", BACKENDS)
def test_shipper_delivers_every_event_once_and_survives_a_broken_exporter(backend):
    pipe = Gst.parse_launch(MAIN.replace("num-buffers=20", "num-buffers=200"))
    tracer = attach(pipe, "node-e", backend=backend, capacity=1 << 12)
    good, broken = MemoryExporter(), BrokenExporter()
    shipper = Shipper(tracer, [broken, good], interval_s=0.01).start()
    run(pipe)
    shipper.stop()
    assert not shipper._thread.is_alive()
    assert good.calls[0] == "start" and good.calls[-1] == "close" and good.header is tracer.header
    assert good.dropped == 0 and good.calls.count("write") >= 1
    ev = np.concatenate(good.batches)
    assert keys(ev) == sorted((st, p, 3, f) for st, p in MAIN_PATH for f in range(200))
    assert shipper.shipped == len(ev)
    assert len(shipper.errors) == 1 and "BrokenExporter" in shipper.errors[0] and "disk full" in shipper.errors[0]
    assert broken.calls == ["start"]


def test_shipper_reports_drops_at_close():
    pipe = Gst.parse_launch(MAIN)
    tracer = attach(pipe, "node-f", capacity=8)
    out = MemoryExporter()
    shipper = Shipper(tracer, [out], interval_s=10).start()  # nothing drained while running
    run(pipe)
    shipper.stop()
    assert sum(len(b) for b in out.batches) == 8
    assert out.dropped == 20 * len(MAIN_PATH) + 2 * 20 + 2 - 8  # + a ready per exit, a thread fact per stage


def test_hooks_and_pad_probes_write_the_same_records():
    """One native core behind both triggers: the tracer's hooks (the default, and what
    GST_TRACERS=dcuscope uses in any application) and pad probes write the same records, ready
    points and their buffer groups included; only the times differ."""
    runs = {t: traced_run(MAIN, "native", trigger=t) for t in native.TRIGGERS}
    assert {t: tr.trigger for t, (tr, _) in runs.items()} == {"hooks": "hooks", "probes": "probes"}
    assert runs["hooks"][0].header.versions["trigger"] == "hooks"

    def records(ev):
        frames = ev[ev["point"] <= READY]
        facts = ev[ev["point"] == FACT]
        return (sorted(zip(*(frames[c].tolist() for c in ("stage", "point", "source", "frame", "code")))),
                sorted(zip(facts["stage"].tolist(), facts["code"].tolist())))

    assert records(runs["hooks"][1]) == records(runs["probes"][1])
    assert len(runs["hooks"][1]) == len(runs["probes"][1]) >= 20 * len(MAIN_PATH)


def test_a_config_can_ask_for_pad_probes(tmp_path):
    """probes.trigger: probes in the YAML: the same run through pad probes, said in the summary."""
    from tests.conftest import run_cli

    config = tmp_path / "p.yaml"
    config.write_text("sources:\n  - test: ball\nstages:\n  - queue: {}\nprobes: {trigger: probes}\n")
    result = run_cli("run", config, "--probes", "--trace", tmp_path / "t.jsonl", "--num-frames", "20")
    assert result.returncode == 0, result.stderr
    assert "(native, probes)" in result.stderr
    from dcuscope.probes.trace.tracefile import read_trace

    assert read_trace(tmp_path / "t.jsonl").header.versions["trigger"] == "probes"
