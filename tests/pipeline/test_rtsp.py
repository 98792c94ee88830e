"""Live RTSP streams served on loopback by dcuscope serve-rtsp, processed end to end with probes."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time

import numpy as np

from dcuscope.model.delays import chains
from dcuscope.model.frametable import frame_table
from dcuscope.probes.trace.tracefile import TraceError, read_trace
from dcuscope.protocol.events import ORIGIN
from tests.conftest import BIKES, VTEST, cli_env, run_cli
from tests.pipeline.clips import MJPEG_MULTIPART, write_clip
from tests.pipeline.livecheck import check_every_frame_accounted, run_timed
from tests.ports import free_port

CLIP_FRAMES = 20  # two seconds at 10 frames/s


def serve(*clips, port: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "serve-rtsp", *map(str, clips), "--port", str(port)],
                            env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert f"rtsp://127.0.0.1:{port}/cam0" in proc.stdout.readline()
    return proc


def run(config, trace, duration, cwd) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config), "--probes", "--trace", str(trace),
                             "--duration", str(duration)], cwd=cwd, env=cli_env(), stderr=subprocess.PIPE, text=True)


def origins_of(trace, source: int, since_ns: int = 0) -> int:
    """Frames of ``source`` stamped (origin events) after ``since_ns``, in a trace still being written."""
    try:
        events = read_trace(trace).events
    except TraceError:  # not written yet
        return 0
    return int(((events["point"] == ORIGIN) & (events["source"] == source) & (events["ts"] > since_ns)).sum())


def wait_for_origins(node: subprocess.Popen, trace, source: int, frames: int, since_ns: int = 0,
                     timeout: float = 90) -> None:
    """Until the running node's trace holds ``frames`` frames of ``source`` stamped after ``since_ns``:
    a stream's first frames take seconds more on a busy machine than on a quiet one."""
    deadline = time.monotonic() + timeout
    while origins_of(trace, source, since_ns) < frames:
        assert node.poll() is None, f"the node ended: {node.stderr.read()}"
        assert time.monotonic() < deadline, f"not {frames} frames of source {source} within {timeout} s"
        time.sleep(0.2)


def stop(node: subprocess.Popen) -> str:
    """SIGTERM, the clean stop; the node's stderr."""
    node.send_signal(signal.SIGTERM)
    return node.communicate(timeout=60)[1]


def test_rtsp_streams_are_processed_end_to_end_with_probes(tmp_path):
    port = free_port()
    server = serve(VTEST, BIKES, port=port)
    try:
        config = tmp_path / "rtsp.yaml"
        config.write_text(
            f"sources:\n  - uri: rtsp://127.0.0.1:{port}/cam0\n  - uri: rtsp://127.0.0.1:{port}/cam1\n"
            "stages:\n  - mux: {batch-size: 2, width: 320, height: 240, live-source: true}\n"
            "  - tiler: {rows: 1, columns: 2, width: 640, height: 240}\n  - convert: {format: RGBA}\n  - osd: {}\n"
        )
        node = run(config, tmp_path / "t.jsonl", 8, tmp_path)
        _, stderr = node.communicate(timeout=60)
        assert node.returncode == 0, stderr
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(10)
    trace = read_trace(tmp_path / "t.jsonl")
    table = frame_table(trace.header, trace.events)
    ch = chains(table)
    fps = {}
    for source, rate in ((0, 10.0), (1, 25.0)):  # the clips' own rates, paced live by the server
        rows = ch.complete & (table.source == source)
        assert rows.sum() >= rate * 3, (source, rows.sum())
        origins = np.sort(table.origin[rows])
        fps[source] = (len(origins) - 1) / ((origins[-1] - origins[0]) / 1e9)
    assert abs(fps[0] - 10) < 2 and abs(fps[1] - 25) < 4, fps


def test_rtsp_streams_a_pipeline_cannot_keep_up_with_stop_at_the_duration_every_frame_accounted(tmp_path):
    """The two shipped clips, 35 frames/s, into a stage that takes about 13: the backlog grows
    in the mux and in rtspsrc's jitter buffer, and an end-of-stream sent into rtspsrc came out
    behind all of it (the run drained until killed). Now it ends at its --duration."""
    port = free_port()
    server = serve(VTEST, BIKES, port=port)
    try:
        config = tmp_path / "behind.yaml"
        config.write_text(
            f"sources:\n  - {{uri: 'rtsp://127.0.0.1:{port}/cam0', latency: 200}}\n"
            f"  - {{uri: 'rtsp://127.0.0.1:{port}/cam1', latency: 200}}\n"
            "stages:\n  - mux: {batch-size: 2, width: 320, height: 240, live-source: true}\n"
            "  - factory: identity\n    properties: {sleep-time: 150000}\n"
        )
        trace = tmp_path / "behind.jsonl"
        run = run_timed("run", config, "--probes", "--trace", trace, "--duration", 8, cwd=tmp_path,
                        stop_line="stopping (--duration 8 s)")
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(10)
    assert run.returncode == 0, run.stderr
    assert run.stop_said_at is not None and run.ended_at - run.stop_said_at < 5.0, run.stderr
    dropped = check_every_frame_accounted(trace)
    assert set(dropped) == {"stopped"} and dropped["stopped"] > 0, dropped


def test_killing_the_rtsp_server_leaves_the_other_source_running_and_reports_the_loss(tmp_path):
    port = free_port()
    server = serve(VTEST, port=port)
    config = tmp_path / "mixed.yaml"
    config.write_text(
        f"sources:\n  - uri: rtsp://127.0.0.1:{port}/cam0\n  - {{test: ball, live: true, rate: 10}}\n"
        "stages:\n  - mux: {batch-size: 2, width: 320, height: 240, live-source: true}\n  - queue: {}\n"
    )
    trace = tmp_path / "t.jsonl"
    node = run(config, trace, 180, tmp_path)  # a bound only: stopped below
    try:
        wait_for_origins(node, trace, 0, 10)  # the stream is flowing
        server.kill()
        killed_at = time.time_ns()
        server.wait(10)
        wait_for_origins(node, trace, 1, 40, killed_at + 2_000_000_000)  # the test source goes on
        stderr = stop(node)
    finally:
        server.kill()
        node.kill()
    assert node.returncode == 0, stderr
    assert "source 0 (uri:rtsp://" in stderr and "was lost" in stderr and "Traceback" not in stderr
    events = read_trace(tmp_path / "t.jsonl").events
    origins = events[events["point"] == ORIGIN]
    before = origins[origins["ts"] < killed_at]
    after = origins[origins["ts"] > killed_at + 2_000_000_000]
    assert (before["source"] == 0).sum() >= 10  # the stream was flowing before the kill
    assert (after["source"] == 0).sum() == 0 and (after["source"] == 1).sum() >= 40  # the test source went on


def test_a_stalled_stream_is_reported_while_the_others_go_on_and_its_return_too(tmp_path):
    port = free_port()
    server = serve(VTEST, port=port)
    try:
        config = tmp_path / "stall.yaml"
        config.write_text(
            f"sources:\n  - uri: rtsp://127.0.0.1:{port}/cam0\n    stall-timeout: 2\n    latency: 200\n"
            "  - {test: ball, live: true, rate: 10}\n"
            "stages:\n  - mux: {batch-size: 2, width: 320, height: 240, live-source: true}\n  - queue: {}\n"
        )
        trace = tmp_path / "t.jsonl"
        node = run(config, trace, 180, tmp_path)  # a bound only: stopped below
        wait_for_origins(node, trace, 0, 10)  # the stream is flowing
        server.send_signal(signal.SIGSTOP)  # the server freezes: no error, no EOS, just no frames
        stopped_at = time.time_ns()
        time.sleep(7)
        server.send_signal(signal.SIGCONT)
        resumed_at = time.time_ns()
        wait_for_origins(node, trace, 0, 10, resumed_at)  # the stream came back
        stderr = stop(node)
    finally:
        node.kill()
        server.send_signal(signal.SIGCONT)
        server.send_signal(signal.SIGINT)
        server.wait(10)
    assert node.returncode == 0, stderr
    assert "source 0 (uri:rtsp://" in stderr and "stalled: no frame for 2." in stderr, stderr
    # A stream slower to start than its stall-timeout (a busy machine) is a stall too, reported as such.
    slow_start = f"source 0 (uri:rtsp://127.0.0.1:{port}/cam0) stalled: no frame yet" in stderr
    times = "2 times" if slow_start else "once"
    assert f"source 0 (uri:rtsp://127.0.0.1:{port}/cam0) stalled {times}," in stderr, stderr
    assert "resumed after" in stderr and "Traceback" not in stderr, stderr
    assert "was lost" not in stderr
    origins = read_trace(tmp_path / "t.jsonl").events
    origins = origins[origins["point"] == ORIGIN]
    # Source 0 went silent for the freeze while source 1 went on: the longest gap between source 0's
    # frames spans the resume and is most of the freeze's 7 s. No fixed time after the freeze is
    # asked: frames sent before it come out late on a loaded machine (in CI runs of the suite one
    # came out 0.5, 1.5 and once more than 3 s after), while those after the resume need not.
    ts = np.sort(origins[origins["source"] == 0]["ts"])
    longest = int(np.argmax(np.diff(ts)))
    gap_from, gap_to = ts[longest], ts[longest + 1]
    assert gap_from < resumed_at < gap_to and gap_to - gap_from > 3_000_000_000, (stopped_at, resumed_at, gap_from, gap_to)
    frozen = origins[(origins["ts"] > stopped_at) & (origins["ts"] < resumed_at)]
    assert (frozen["source"] == 1).sum() >= 28  # of 70 at 10 fps for 7 s: fewer on a loaded machine
    after = origins[origins["ts"] > resumed_at]
    assert (after["source"] == 0).sum() >= 10  # the stream came back


def test_rtsp_latency_from_the_config_reaches_rtspsrc(tmp_path, gst_registered):
    from dcuscope.core.gst import Gst
    from dcuscope.pipeline.build import build_pipeline
    from dcuscope.pipeline.config import load_config

    port = free_port()
    server = serve(VTEST, port=port)
    config = tmp_path / "latency.yaml"
    config.write_text(f"sources:\n  - uri: rtsp://127.0.0.1:{port}/cam0\n    latency: 123\nstages:\n  - queue: {{}}\n")
    built = build_pipeline(load_config(config))
    try:
        built.pipeline.set_state(Gst.State.PLAYING)
        found = None
        for _ in range(100):
            found = [e for e in built.pipeline.iterate_recurse() if e.__gtype__.name == "GstRTSPSrc"]
            if found:
                break
            time.sleep(0.05)
        assert found and found[0].get_property("latency") == 123
    finally:
        built.pipeline.set_state(Gst.State.NULL)
        server.send_signal(signal.SIGINT)
        server.wait(10)


def test_serve_rtsp_refuses_what_is_not_a_video(tmp_path):
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n")
    result = run_cli("serve-rtsp", text, "--port", str(free_port()), timeout=60)
    assert result.returncode != 0 and "cannot read it as video" in result.stderr and "Traceback" not in result.stderr


def test_serve_rtsp_puts_a_key_frame_every_second_of_the_clip():
    from dcuscope.pipeline.rtsp import keyframe_interval

    assert keyframe_interval(BIKES) == 25 and keyframe_interval(VTEST) == 10


def rtsp_config(path, port: int, *more: str) -> str:
    path.write_text(f"sources:\n  - {{uri: 'rtsp://127.0.0.1:{port}/cam0', latency: 200}}\n" + "".join(more)
                    + "stages:\n  - mux: {batch-size: 2, width: 320, height: 240, live-source: true}\n  - queue: {}\n")
    return path


def frames_and_seconds(stderr: str) -> tuple[int, float]:
    frames, seconds = re.search(r"(\d+) frames in ([\d.]+) s", stderr).groups()
    return int(frames), float(seconds)


def test_serve_rtsp_loops_a_short_clip_for_longer_than_its_length(tmp_path):
    """The server's stream used to announce the clip's length (Range: npt=0-2), and rtspsrc ended it there."""
    clip = write_clip(tmp_path / "two.mp4", CLIP_FRAMES)
    port = free_port()
    server = serve(clip, port=port)
    try:
        result = run_cli("run", rtsp_config(tmp_path / "loop.yaml", port), "--duration", "7", cwd=tmp_path, timeout=60)
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(10)
    assert result.returncode == 0, result.stderr
    assert "ended" not in result.stderr and "stalled" not in result.stderr, result.stderr
    frames, seconds = frames_and_seconds(result.stderr)
    assert seconds >= 6.9 and frames >= 2.5 * CLIP_FRAMES, (frames, seconds)  # 10 frames/s, past the third loop


def test_a_stream_that_the_server_ends_is_reported_and_the_others_go_on(tmp_path):
    """A clip that cannot loop (no length) makes the server end its stream: the consumer says so."""
    clip = write_clip(tmp_path / "clip.mjpeg", CLIP_FRAMES, MJPEG_MULTIPART)
    port = free_port()
    server = serve(clip, port=port)
    try:
        config = rtsp_config(tmp_path / "ends.yaml", port, "  - {test: ball, live: true, rate: 10}\n")
        result = run_cli("run", config, "--duration", "6", cwd=tmp_path, timeout=60)
    finally:
        server.send_signal(signal.SIGINT)
        _, served = server.communicate(timeout=10)
    assert f"warning: cam0 ({clip}): cannot loop: its length is unknown" in served, served  # the server says why
    assert result.returncode == 0, result.stderr
    assert f"source 0 (uri:rtsp://127.0.0.1:{port}/cam0) ended: end of stream after " in result.stderr, result.stderr
    assert "; the other sources go on" in result.stderr and frames_and_seconds(result.stderr)[1] >= 5.9


def test_a_refused_rtsp_connection_names_the_source_and_says_what_to_check(tmp_path):
    port = free_port()  # nothing listens there
    result = run_cli("run", rtsp_config(tmp_path / "refused.yaml", port), "--duration", "5", cwd=tmp_path, timeout=60)
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
    assert (f"dcuscope: error: source 0 (uri:rtsp://127.0.0.1:{port}/cam0): " in result.stderr
            and f"check that an RTSP server is running at 127.0.0.1:{port}, that it serves the path /cam0, "
                f"and that no firewall blocks port {port}" in result.stderr), result.stderr


def test_a_wrong_rtsp_path_is_named_while_the_others_go_on(tmp_path):
    port = free_port()
    server = serve(VTEST, port=port)
    try:
        config = rtsp_config(tmp_path / "path.yaml", port, "  - {test: ball, live: true, rate: 10}\n")
        config.write_text(config.read_text().replace("/cam0", "/cam7"))
        result = run_cli("run", config, "--duration", "3", cwd=tmp_path, timeout=60)
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(10)
    assert result.returncode == 0, result.stderr
    assert (f"source 0 (uri:rtsp://127.0.0.1:{port}/cam7) failed: Not found (Not Found (404)): the server at "
            f"127.0.0.1:{port} has no stream at /cam7: check the path; the other sources go on") in result.stderr, result.stderr


def test_an_rtsp_frame_carries_its_capture_time_to_its_framestamp(tmp_path, gst_registered):
    """The sender's capture time (RTCP sender reports -> the jitter buffer's timestamp/x-ntp meta)
    survives depayloading, decoding and conversion: a realtime value just before the origin."""
    from dcuscope.core.gst import Gst
    from dcuscope.pipeline.build import build_pipeline
    from dcuscope.pipeline.config import load_config
    from dcuscope.plugins.frames import capture_ns, read_frames

    port = free_port()
    started = time.clock_gettime_ns(time.CLOCK_REALTIME)
    server = serve(VTEST, port=port)
    config = tmp_path / "capture.yaml"
    config.write_text(f"sources:\n  - uri: rtsp://127.0.0.1:{port}/cam0\n    latency: 200\nstages:\n  - queue: {{}}\n")
    built = build_pipeline(load_config(config))
    seen = []  # (capture or None, origin, arrival)

    def stamped(_pad, info):
        buf = info.get_buffer()
        seen.append((capture_ns(buf), read_frames(buf)[0].origin_ns, time.clock_gettime_ns(time.CLOCK_REALTIME)))
        return Gst.PadProbeReturn.OK

    built.sources[0].stamp.get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER, stamped)
    try:
        built.pipeline.set_state(Gst.State.PLAYING)
        deadline = time.monotonic() + 30
        while sum(c is not None for c, _, _ in seen) < 20 and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        built.pipeline.set_state(Gst.State.NULL)
        server.send_signal(signal.SIGINT)
        server.wait(10)
    timed = [(c, o, a) for c, o, a in seen if c is not None]
    assert len(timed) >= 20, f"{len(timed)} of {len(seen)} frames had a capture time"
    assert all(started < c < o <= a for c, o, a in timed)  # before its origin, after the server started
    # One per frame, 100 ms apart as the server's 10 fps clip: the sender's frame times, not its reports'.
    steps = np.diff([c for c, _, _ in timed])
    assert abs(np.median(steps) - 100_000_000) < 1_000_000, steps
