"""benchmarks/streams_sweep.py: its pure parts on synthetic events, and one real sweep (file and
RTSP, one 1080p stream, the SSD model) at the smallest settings."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2

from benchmarks.plot import STAGE_COLOURS, draw_sweep, nice_step
from benchmarks.streams_sweep import (
    STAGES, ClipSpec, Result, after_warmup, combine, config_text, grid, make_clip, markdown, measure, saturated,
    series,
)
from pipeline.config import load_config
from probes.events import EXIT
from probes.tracefile import Trace
from tests.conftest import REPO, VTEST, cli_env
from tests.probes.synth import pipeline_run

MS = 1_000_000


def slow_start_run():
    """Two 10 fps sources, 30 frames each; infer takes 30 ms, but 330 ms for the first 10 frames."""
    header, events, _ = pipeline_run(30, 2, period_ns=100 * MS, stage_ns=(2 * MS, 30 * MS, 3 * MS, 1 * MS, 4 * MS),
                                     gap_ns=0)
    infer = header.stages.index("infer")
    late = (events["frame"] < 10) & ((events["stage"] > infer) | ((events["stage"] == infer) & (events["point"] == EXIT)))
    events["ts"][late] += 300 * MS
    return Trace(header, events, dropped=0, complete=True)


def test_after_warmup_keeps_every_event_of_the_frames_that_started_after_the_cutoff():
    trace = slow_start_run()
    kept = after_warmup(trace.events, 1.0)
    assert sorted(set(kept["frame"].tolist())) == list(range(10, 30))
    per_frame = len(trace.events) // 60
    assert len(kept) == 40 * per_frame  # whole frames: their late exits stay with them
    assert after_warmup(trace.events, 0).shape == trace.events.shape


def test_measure_leaves_out_the_warmup_and_gives_a_as_the_mean_frame_delay():
    trace = slow_start_run()
    steady = measure(trace, 1.0)
    assert steady.stages_ms == {"mux": 2.0, "infer": 30.0, "tiler": 3.0, "convert": 1.0, "osd": 4.0}
    assert steady.a_ms == 40.0 and steady.queues_ms == 0.0 and steady.frames == 40
    assert steady.fps == 10.0
    everything = measure(trace, 0)
    assert everything.stages_ms["infer"] == (10 * 330 + 20 * 30) / 30
    assert everything.a_ms == 40.0 + 100.0


def test_saturation_is_under_90_percent_of_the_clip_rate():
    assert saturated(26.9, 30) and not saturated(27.0, 30) and not saturated(60.0, 60)


def test_collage_grid_is_as_square_as_possible():
    assert [grid(n) for n in range(1, 8)] == [(1, 1), (1, 2), (2, 2), (2, 2), (2, 3), (2, 3), (3, 3)]


def test_configs_are_valid_dcuscope_configurations(tmp_path):
    file_cfg = tmp_path / "file.yaml"
    file_cfg.write_text(config_text("file", [VTEST.as_uri()] * 3, 30, "ssd"))
    config = load_config(file_cfg)
    assert [s.factory for s in config.stages] == list(STAGES)
    mux, infer, tiler = (s.properties for s in config.stages[:3])
    assert mux == {"batch-size": 3, "width": 1920, "height": 1080}
    assert infer["model"].endswith("ssdlite_mobilenetv2_person.onnx")
    assert (tiler["rows"], tiler["columns"]) == (2, 2)
    assert all(s.loop for s in config.sources) and config.sink.sync

    rtsp_cfg = tmp_path / "rtsp.yaml"
    rtsp_cfg.write_text(config_text("rtsp", ["rtsp://127.0.0.1:9/cam0"], 60, "centernet"))
    config = load_config(rtsp_cfg)
    mux = config.stages[0].properties
    assert mux["live-source"] is True and mux["batched-push-timeout"] == 16666
    assert config.sources[0].location == "rtsp://127.0.0.1:9/cam0" and not config.sink.sync


def result(kind, fps, streams, a_ms, sat=False, bitrate=3982):
    stages = {"mux": a_ms * 0.5, "infer": a_ms * 0.3, "tiler": a_ms * 0.1, "convert": a_ms * 0.05, "osd": a_ms * 0.05}
    return Result(kind, fps, bitrate, streams, a_ms=a_ms, p95_ms=a_ms * 1.5, achieved_fps=fps * (0.5 if sat else 1),
                  stages_ms=stages, queues_ms=0.0, frames=100, saturated=sat)


def test_markdown_has_one_table_per_bitrate_and_the_per_stage_data():
    results = [result("file", 30, 1, 40.0), result("file", 30, 2, 90.0, sat=True), result("rtsp", 30, 1, 120.0),
               result("file", 30, 1, 44.0, bitrate=7955)]
    text = markdown(results, "ssd", ["- machine: test"])
    assert text.startswith("- machine: test\n")
    assert "3982 kbit/s (paper's Table 4)" in text and "7955 kbit/s (paper's Table 6)" in text
    assert "| streams | file 30 fps | rtsp 30 fps |" in text
    assert "| 1 | 40.0 (p95 60) @ 30.0 | 120.0 (p95 180) @ 30.0 |" in text
    assert "| 2 | 90.0 (p95 135) @ 15.0* | – |" in text
    assert "| file | 30 | 3982 | 2 | 45.0 | 27.0 | 9.0 | 4.5 | 4.5 | 0.0 | 90.0 | 135.0 | 15.0* | 0.0 | – |" in text


def test_repetitions_combine_to_medians_and_failed_runs_are_left_out():
    runs = [result("file", 30, 1, 40.0), result("file", 30, 1, 100.0, sat=True), result("file", 30, 1, 50.0),
            Result("file", 30, 3982, 1, error="serve-rtsp did not start")]
    for r, load in zip(runs, (1.0, 3.0, 2.0, 9.0)):
        r.load = load
    c = combine(runs)
    assert (c.a_ms, c.p95_ms, c.achieved_fps, c.load, c.runs, c.frames) == (50.0, 75.0, 30.0, 2.0, 3, 300)
    assert c.stages_ms["mux"] == 25.0 and not c.saturated and c.error == "serve-rtsp did not start"
    assert combine(runs[3:]) is runs[3]


def test_plot_draws_the_stage_colours_and_a_panel_per_series(tmp_path):
    results = [result("file", 30, 1, 40.0), result("file", 30, 2, 90.0), result("rtsp", 30, 1, 120.0),
               result("rtsp", 60, 1, 300.0, sat=True)]
    path = tmp_path / "plot.png"
    img = draw_sweep([r.__dict__ for r in results], path)
    assert (cv2.imread(str(path)) == img).all()
    assert img.shape[0] > img.shape[1] * 0.5  # two rows of panels: file, rtsp
    for colour in STAGE_COLOURS.values():
        assert (img == colour).all(axis=2).sum() > 20, colour
    assert [nice_step(x) for x in (10, 47, 480, 0.9)] == [2, 10, 100, 0.2]


def test_smallest_real_sweep_makes_a_clip_runs_file_and_rtsp_and_reports(tmp_path):
    cache, out = tmp_path / "clips", tmp_path / "sweep.md"
    proc = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "streams_sweep.py"), "--model", "ssd", "--bitrates", "3982",
         "--rates", "30", "--max-streams", "1", "--duration", "4", "--warmup", "1", "--clip-seconds", "2",
         "--cache", str(cache), "--out", str(out)],
        cwd=tmp_path, env=cli_env(), capture_output=True, text=True, timeout=150)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "clips: 1 needed, 1 to make" in proc.stderr and "eta <=" in proc.stderr

    clip = cache / ClipSpec("vtest.avi", 30, 3982, 2).name
    video = cv2.VideoCapture(str(clip))
    assert (video.get(cv2.CAP_PROP_FRAME_WIDTH), video.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (1920, 1080)
    assert video.get(cv2.CAP_PROP_FPS) == 30 and 55 <= video.get(cv2.CAP_PROP_FRAME_COUNT) <= 65
    video.release()
    made = clip.stat().st_mtime_ns
    assert make_clip(ClipSpec("vtest.avi", 30, 3982, 2), cache) == clip and clip.stat().st_mtime_ns == made

    data = json.loads(out.with_suffix(".json").read_text())
    assert [(r["kind"], r["streams"]) for r in data["results"]] == [("file", 1), ("rtsp", 1)]
    for r in data["results"]:
        assert r["error"] == "" and r["frames"] >= 5 and r["achieved_fps"] > 1, r
        assert set(r["stages_ms"]) == set(STAGES) and all(v > 0 for v in r["stages_ms"].values()), r
        # A is measured origin -> sink, the stages separately: A covers them all, plus waits.
        assert r["a_ms"] >= sum(r["stages_ms"].values()) - 0.01 and r["p95_ms"] >= r["a_ms"] * 0.5, r
        assert r["load"] > 0 and r["runs"] == 1
    server = data["results"][1]["server_cores"]
    assert data["results"][0]["server_cores"] is None and 0.05 < server < 4  # decoding + encoding 1080p30
    text = out.read_text()
    assert "3982 kbit/s (paper's Table 4), model ssd" in text and "| streams | file 30 fps | rtsp 30 fps |" in text
    assert text in proc.stdout
    png = cv2.imread(str(out.with_suffix(".png")))
    assert png is not None and (png == STAGE_COLOURS["infer"]).all(axis=2).sum() > 20


def test_series_are_bitrate_major_and_bitrates_at_narrows_a_rate():
    plan = list(series(["file", "rtsp"], [30, 60], [3982, 7955], {60: [3982]}))
    assert plan == [("file", 30, 3982), ("file", 60, 3982), ("rtsp", 30, 3982), ("rtsp", 60, 3982),
                    ("file", 30, 7955), ("rtsp", 30, 7955)]
