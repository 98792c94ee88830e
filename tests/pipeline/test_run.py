"""Real pipelines from the shipped configs, run in-process and through the CLI."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import sysconfig
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from dcuscope.core.gst import Gst, GstVideo
from dcuscope.pipeline.build import build_pipeline
from dcuscope.pipeline.config import SinkConfig, load_config
from dcuscope.pipeline import run as run_module
from dcuscope.pipeline.run import Runner
from dcuscope.plugins.frames import mapped_video, read_frames, read_objects
from tests.conftest import REPO, cli_env, run_cli, wait_until_mapped
from tests.pipeline.clips import decode_video

LIVE_BALL = ("sources:\n  - {test: ball, live: true, width: 320, height: 240, rate: 30}\n"
             "stages:\n  - mux: {width: 320, height: 240}\n  - tiler: {width: 320, height: 240}\n"
             "  - convert: {format: RGBA}\n  - osd: {}\n")
"""A camera-like test pattern through the chain without a model: quick to start, runs until stopped."""


def test_boxes_are_drawn_where_the_detections_are(tmp_path):
    config = replace(load_config(REPO / "configs" / "vtest.yaml"), sinks=(SinkConfig(kind="frames", path=tmp_path / "frames"),))
    built = build_pipeline(config)
    osd = built.pipeline.get_by_name("osd")
    before, detections, identities = [], [], []

    def on_enter(pad, info):
        vinfo = GstVideo.VideoInfo.new_from_caps(pad.get_current_caps())
        with mapped_video(info.get_buffer(), vinfo) as frame:
            before.append(frame[:, :, :3].copy())
        return Gst.PadProbeReturn.OK

    def on_exit(_pad, info):
        detections.append(read_objects(info.get_buffer()))
        identities.append(read_frames(info.get_buffer()))
        return Gst.PadProbeReturn.OK

    osd.get_static_pad("sink").add_probe(Gst.PadProbeType.BUFFER, on_enter)
    osd.get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER, on_exit)
    Runner(built, num_frames=3, progress=None).run()

    pngs = sorted((tmp_path / "frames").glob("frame_*.png"))
    assert len(pngs) == 3 and len(before) >= 3
    assert [ids[0].frame for ids in identities[:3]] == [0, 1, 2]  # identity survived the chain
    for index, png in enumerate(pngs):
        drawn = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)
        original, dets = before[index], detections[index]
        assert drawn.shape == original.shape == (576, 768, 3)
        persons = [i for i, label in enumerate(dets.labels) if label == "person"]
        assert len(persons) >= 3, dets.labels
        changed = np.any(np.abs(drawn.astype(int) - original.astype(int)) > 40, axis=2)
        near_boxes = np.zeros_like(changed)
        for x1, y1, x2, y2 in dets.boxes.astype(int):
            x1, y1 = max(x1, 0), max(y1, 0)
            x2, y2 = min(x2, 767), min(y2, 575)
            # The left and right edges of every box were painted (labels sit on the top edge).
            left, right = changed[y1 + 2:y2 - 1, x1], changed[y1 + 2:y2 - 1, x2]
            assert left.mean() > 0.6 and right.mean() > 0.6, (x1, y1, x2, y2)
            near_boxes[max(y1 - 30, 0):y2 + 4, max(x1 - 4, 0):x2 + 200] = True
        # Away from the boxes and their labels nothing was drawn.
        assert changed[~near_boxes].mean() < 0.002


@pytest.mark.long
def test_quad_demo_writes_a_playable_2x2_collage(tmp_path):
    out = tmp_path / "quad.mp4"
    result = run_cli("run", REPO / "configs" / "quad.yaml", "--output", out, "--num-frames", "20", cwd=tmp_path,
                     timeout=400)
    assert result.returncode == 0, result.stderr
    assert "20 frames" in result.stderr
    frames = decode_video(out)
    assert len(frames) == 20
    assert frames[0].shape == (720, 1280, 3)
    # Each camera in its own tile: vtest (sources 0, 2) on the left, bikes (1, 3) on the right.
    last = frames[-1].astype(float)
    tiles = [last[:360, :640], last[:360, 640:], last[360:, :640], last[360:, 640:]]
    for a, b in ((0, 1), (0, 3), (2, 1), (2, 3)):
        assert np.abs(tiles[a] - tiles[b]).mean() > 10


def draining(tmp_path: Path, sleep_ms: int) -> Runner:
    """A fast test pattern, a queue of 20 frames and a stage that sleeps ``sleep_ms`` per frame: at
    a stop, end-of-stream waits behind the queue's backlog."""
    config = tmp_path / "draining.yaml"
    config.write_text("sources:\n  - {test: ball, width: 160, height: 120, rate: 30}\nstages:\n"
                      "  - queue: {max-size-buffers: 20, max-size-bytes: 0, max-size-time: 0}\n"
                      f"  - {{factory: identity, properties: {{sleep-time: {sleep_ms * 1000}}}}}\n")
    return Runner(build_pipeline(load_config(config)), num_frames=1, progress=None)


def stuck_after_the_first_frame(runner: Runner) -> Runner:
    """Nothing passes the queue after the first frame, end-of-stream included: a stuck pipeline."""
    queue = runner.built.stages[0]  # draining()'s first stage
    passed = []

    def hold(_pad, info):
        if passed:
            return Gst.PadProbeReturn.DROP
        if info.type & Gst.PadProbeType.BUFFER:
            passed.append(True)
        return Gst.PadProbeReturn.OK
    queue.get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER | Gst.PadProbeType.EVENT_DOWNSTREAM, hold)
    return runner


@pytest.mark.parametrize("after_first_frame", [True, False])
def test_a_duration_after_the_first_frame_is_not_eaten_by_a_slow_start(tmp_path, after_first_frame):
    # A capacity count (dcuscope/capacity/count.py) measures --duration from its first frame: a start
    # that a loaded machine slows (here the first frame held 1.5 s, timed where it is held) leaves the
    # measured time whole. `dcuscope run --duration` counts from PLAYING, as before.
    config = tmp_path / "slow-start.yaml"
    config.write_text("sources:\n  - {test: ball, width: 160, height: 120, rate: 30}\nstages:\n  - queue: {}\n")
    built = build_pipeline(load_config(config))
    runner = Runner(built, duration=1.0, progress=None, duration_after_first_frame=after_first_frame)
    held: list[float] = []

    def hold_the_first(_pad, _info):
        if not held:
            time.sleep(1.5)
            held.append(time.monotonic())  # the first frame goes on now
        return Gst.PadProbeReturn.OK
    built.stages[0].get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER, hold_the_first)
    result = runner.run()
    ended = time.monotonic()
    assert result.aborted is None and held, result
    if after_first_frame:
        assert ended - held[0] >= 1.0 and result.frames >= 10, (ended - held[0], result)
    else:
        assert ended - held[0] < 1.0, (ended - held[0], result)


def test_a_stop_waits_for_a_pipeline_that_still_drains_and_not_for_a_stuck_one(tmp_path, monkeypatch):
    monkeypatch.setattr(run_module, "EOS_GRACE_S", 1.0)
    # A frame every 0.1 s: 20 queued frames take 2 s, twice the grace, and end-of-stream comes.
    result = draining(tmp_path, 100).run()
    assert result.aborted is None and result.frames == 1 and result.seconds >= 2.0, result
    # Nothing reaches the sink after the first frame, nor end-of-stream: the run gives up after the
    # grace (frames that still come, however far apart, are a pipeline draining: the next test).
    result = stuck_after_the_first_frame(draining(tmp_path, 100)).run()
    assert result.aborted == "end-of-stream did not reach the sink" and result.frames == 1, result
    assert result.past_limit == 0, result


def test_a_stop_waits_longer_where_frames_come_further_apart_than_the_grace(tmp_path, monkeypatch):
    """A slow DCU (a detector at a frame in 20 s under emulation): frames 1.2 s apart, more than the
    1 s grace; after three, the stop waits for the two still in flight (three times the longest gap)."""
    monkeypatch.setattr(run_module, "EOS_GRACE_S", 1.0)
    config = tmp_path / "slow.yaml"
    config.write_text("sources:\n  - {test: ball, width: 160, height: 120, rate: 30}\nstages:\n"
                      "  - queue: {max-size-buffers: 1, max-size-bytes: 0, max-size-time: 0}\n"
                      "  - {factory: identity, properties: {sleep-time: 1200000}}\n")
    result = Runner(build_pipeline(load_config(config)), num_frames=3, progress=None).run()
    assert result.aborted is None and result.frames == 3 and result.past_limit >= 1, result


def test_ctrl_c_ends_the_run_cleanly_and_finalises_the_video(tmp_path):
    out = tmp_path / "live.mp4"
    config = tmp_path / "ball.yaml"
    config.write_text(LIVE_BALL)
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config), "--output", str(out)],
                            cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE, text=True)
    time.sleep(4)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    assert "stopping: sending end-of-stream" in stderr and "Traceback" not in stderr
    frames = decode_video(out)
    assert 30 <= len(frames) <= 200  # about 4 s at 30 fps, and the MP4 is finalised


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_ctrl_c_while_the_run_is_starting_stops_it_cleanly(tmp_path, signum):
    """The signal lands while GStreamer and our elements load (without a handler it raised
    KeyboardInterrupt in PyGObject's type registration, which aborts the process)."""
    config = tmp_path / "ball.yaml"
    config.write_text("sources:\n  - {test: ball, width: 320, height: 240}\n"
                      "stages:\n  - mux: {width: 320, height: 240}\n  - infer: {}\n"
                      "  - tiler: {width: 320, height: 240}\n  - convert: {format: RGBA}\n  - osd: {}\n")
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config), "--probes"],
                            cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE, text=True)
    wait_until_mapped(proc, "libgstreamer-1.0")
    proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    name = signal.Signals(signum).name
    assert f"{name} while starting" in stderr and "stopped before the pipeline started" in stderr, stderr
    assert "Traceback" not in stderr and "ERROR" not in stderr, stderr


@pytest.mark.parametrize("stop", ["duration", "SIGTERM"])
def test_a_run_whose_stderr_went_away_still_stops(tmp_path, stop):
    """``dcuscope run ... 2>&1 | head`` or a dropped ssh session: writing progress to a closed pipe
    raised inside the main loop's callbacks and took --duration and the SIGTERM handler with it."""
    config = tmp_path / "ball.yaml"
    config.write_text(LIVE_BALL)
    limit = ["--duration", "3"] if stop == "duration" else []
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config), *limit],
                            cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE)
    proc.stderr.close()  # nobody reads its messages any more: each write is a broken pipe
    if stop == "SIGTERM":
        time.sleep(3)
        proc.send_signal(signal.SIGTERM)
    try:
        assert proc.wait(timeout=30) == 0
    finally:
        proc.kill()


def test_gst_launch_uses_the_five_elements_by_name():
    env = cli_env()
    env["GST_PLUGIN_PATH"] = str(REPO / "plugins" / "loader")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), sysconfig.get_paths()["purelib"]])
    env["GST_REGISTRY"] = str(Path(env.get("TMPDIR", "/tmp")) / f"dcuscope-registry-{os.getpid()}.bin")
    line = ("videotestsrc num-buffers=3 ! video/x-raw,format=RGB,width=320,height=240 ! "
            "mux name=m batch-size=1 width=320 height=240 ! infer threshold=0.3 ! "
            "tiler rows=1 columns=1 width=320 height=240 ! convert format=RGBA ! osd ! fakesink")
    # --no-fault: a crash ends gst-launch with its signal instead of spinning until gdb comes. (The
    # rare SIGSEGVs once seen here were gst-python's loader writing into the sys.path list that cv2
    # had replaced: see plugins.loading and tests/plugins/test_gst_launch_concurrent.py.)
    result = subprocess.run(["gst-launch-1.0", "--no-fault", *line.split()], env=env, capture_output=True, text=True,
                            timeout=180)
    assert result.returncode == 0, f"exit {result.returncode}\n{result.stdout}{result.stderr}"
    assert "Execution ended" in result.stdout


def test_a_pipeline_error_stops_the_run_with_a_message(tmp_path):
    config = tmp_path / "bad.yaml"
    config.write_text(
        "sources:\n  - {test: ball, width: 320, height: 240}\n"
        "stages:\n  - mux: {width: 320, height: 240}\n  - convert: {format: RGBA}\n"
    )
    result = run_cli("run", config, "--num-frames", "5", cwd=tmp_path, timeout=60)
    assert result.returncode == 2, result.stderr  # mux batches cannot go into convert
    assert "mux cannot be linked to convert" in result.stderr and "Traceback" not in result.stderr


def test_help_explains_the_run_command():
    result = run_cli("run", "--help", timeout=60)
    assert result.returncode == 0
    for words in ("--num-frames", "--duration", "--output", "--probes", "Ctrl-C", "examples"):
        assert words in result.stdout


def test_live_files_write_a_playable_mp4(tmp_path):
    """Live files (paced by clocksync, like cameras) into an MP4: a camera that missed the mux's
    timeout made a batch with a PTS that did not grow, and mp4mux stopped the run."""
    config = tmp_path / "live.yaml"
    config.write_text(f"sources:\n  - {{uri: {REPO / 'assets/media/vtest.avi'}, rate: 10, live: true}}\n"
                      f"  - {{uri: {REPO / 'assets/media/bikes.mp4'}, rate: 10, live: true}}\n"
                      "stages:\n  - mux: {width: 320, height: 180, batched-push-timeout: 1000}\n"
                      "  - tiler: {rows: 1, columns: 2, width: 640, height: 180}\n  - convert: {format: RGBA}\n"
                      "  - osd: {}\n")
    out = tmp_path / "live.mp4"
    result = run_cli("run", config, "--output", out, "--num-frames", "20", cwd=tmp_path, timeout=120)
    assert result.returncode == 0 and "Could not multiplex" not in result.stderr, result.stderr
    assert len(decode_video(out)) == 20


BALL = ("sources:\n  - {test: ball, width: 160, height: 120}\n"
        "stages:\n  - mux: {width: 160, height: 120}\n  - tiler: {width: 160, height: 120}\n"
        "  - convert: {format: RGBA}\n  - osd: {}\n")
"""A test pattern through the chain without a model: a few frames in a second."""


@pytest.mark.parametrize("output,expected", [
    ("missing/dir/x.mp4", "folder {tmp}/missing/dir does not exist"),
    ("/proc/x.mp4", "cannot be written"),
    ("x.txt", "unknown video container '.txt'"),
    ("old/", "already holds frame_*.png frames of an earlier run"),
    ("missing/frames/", "folder {tmp}/missing does not exist"),
], ids=["missing folder", "unwritable", "unknown container", "old frames", "frames in a missing folder"])
def test_a_bad_output_path_exits_2_before_the_run(tmp_path, output, expected):
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "frame_00000.png").write_bytes(b"an earlier run")
    config = tmp_path / "ball.yaml"
    config.write_text(BALL)
    result = run_cli("run", config, "--output", output, "-n", "3", cwd=tmp_path, timeout=60)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"dcuscope: error: --output {output.rstrip('/')}: "), lines
    assert expected.format(tmp=tmp_path) in lines[0]
    assert not (tmp_path / "missing").exists() and sorted(p.name for p in (tmp_path / "old").iterdir()) == [
        "frame_00000.png"]


@pytest.mark.parametrize("suffix,magic", [(".mkv", b"\x1a\x45\xdf\xa3"), (".avi", b"RIFF")])
def test_the_output_name_picks_the_container(tmp_path, suffix, magic):
    config = tmp_path / "ball.yaml"
    config.write_text(BALL)
    out = tmp_path / f"x{suffix}"
    result = run_cli("run", config, "--output", out, "-n", "3", cwd=tmp_path, timeout=60)
    assert result.returncode == 0, result.stderr
    assert out.read_bytes()[:4] == magic  # not an MP4 (ftyp) under another name


def test_a_second_ctrl_c_says_the_video_is_incomplete_and_exits_non_zero(tmp_path):
    """Aborted before end-of-stream reached mp4mux, the MP4 has no index (moov): the run said
    "output: ..." and exited 0 as if it had been written."""
    config = tmp_path / "slow.yaml"  # the frame inside a slow stage holds end-of-stream for seconds
    config.write_text(LIVE_BALL + "  - factory: identity\n    properties: {sleep-time: 3000000}\n")
    out = tmp_path / "x.mp4"
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config), "--output", str(out)],
                            cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:
        if "frames" in line:  # a progress line: the run's main loop, and its Ctrl-C handler, are on
            break
    proc.send_signal(signal.SIGINT)
    for line in proc.stderr:
        if "stopping: sending end-of-stream" in line:
            break
    proc.send_signal(signal.SIGINT)
    stderr = proc.stderr.read()
    assert proc.wait(timeout=30) == 130, stderr
    assert f"{out} is incomplete" in stderr and "output:" not in stderr, stderr
    assert b"moov" not in out.read_bytes()
