"""benchmarks/streams_sweep.py, the caller of ``dcuscope capacity`` with the paper's clips: its
clips, configs and Markdown on hand-made capacity documents, and one real sweep (file and RTSP,
one stream, the SSD model) at the smallest settings: 320x180 frames, 1.5 s per count."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import pytest

from benchmarks.figures import run
from benchmarks.streams_sweep import (
    STAGES, ClipSpec, capacity_command, clip_for, config_text, main, make_clip, markdown, parse_args, series,
)
from dcuscope.pipeline.config import load_config
from tests.benchmarks.smoke import assert_cannot_run, assert_every_na_has_a_reason, run_benchmark
from tests.conftest import REPO, VTEST, cli_env


def test_clips_are_named_by_source_size_rate_bitrate_length_and_preset_and_cycle_the_two_sources():
    assert ClipSpec("bikes.mp4", 60, 7955, 10).name == "bikes_1080p60_7955k_10s_superfast.mp4"
    assert ClipSpec("vtest.avi", 30, 3982, 2, width=320, height=200).name == "vtest_320x200p30_3982k_2s_superfast.mp4"
    assert [clip_for(i, 30, 3982, 10, "fast").source for i in range(3)] == ["vtest.avi", "bikes.mp4", "vtest.avi"]


def test_configs_are_valid_dcuscope_configurations_of_the_papers_chain(tmp_path):
    cfg = tmp_path / "file.yaml"
    cfg.write_text(config_text("file", [VTEST, VTEST], 30, "ssd"))
    config = load_config(cfg)
    assert [s.factory for s in config.stages] == list(STAGES) and config.sink.kind == "fake"
    mux, infer, tiler = (s.properties for s in config.stages[:3])
    assert mux == {"batch-size": 1, "width": 1920, "height": 1080}  # capacity sets the batch and widens the grid
    assert infer["model"].endswith("ssdlite_mobilenetv2_person.onnx")
    assert (tiler["rows"], tiler["columns"], tiler["width"]) == (1, 1, 1920)
    assert [s.location for s in config.sources] == [VTEST.as_uri()] * 2 and all(s.loop for s in config.sources)

    cfg.write_text(config_text("rtsp", [VTEST], 60, "centernet", size=(320, 180)))
    mux, infer, tiler = (s.properties for s in load_config(cfg).stages[:3])
    assert mux == {"batch-size": 1, "width": 320, "height": 180, "batched-push-timeout": 16666}
    assert infer["model"].endswith("centernet_mobilenetv3_coco80.onnx") and tiler["height"] == 180
    cfg.write_text(config_text("rtsp-late", [VTEST], 30, "ssd", late_ms=150))
    assert load_config(cfg).stages[0].properties["max-latency"] == 150


def test_series_are_bitrate_major_and_the_quick_run_keeps_a_given_duration(tmp_path):
    assert series(["file", "rtsp"], [30, 60], [3982, 7955])[:3] == [("file", 30, 3982), ("file", 60, 3982),
                                                                     ("rtsp", 30, 3982)]
    quick = parse_args(["--quick"])
    assert (quick.bitrates, quick.rates, quick.max_streams, quick.duration, quick.warmup) == ([3982], [30], 2, 8.0, 3.0)
    args = parse_args(["--quick", "--duration", "10", "--max-streams", "3"])
    assert (args.duration, args.warmup, args.max_streams) == (10.0, 3.0, 2)
    cmd = capacity_command(tmp_path / "c.yaml", "rtsp-late", args, tmp_path / "c.json", tmp_path / "c.png", 4971)
    assert cmd[1:] == ["-m", "dcuscope.cli", "capacity", str(tmp_path / "c.yaml"), "--max-streams", "2", "--duration",
                       "10", "--warmup", "3", "--json", "-o", str(tmp_path / "c.json"), "--rtsp", "--rtsp-bitrate",
                       "4971", "--plot", str(tmp_path / "c.png")]
    assert "--rtsp" not in capacity_command(tmp_path / "c.yaml", "file", args, tmp_path / "c.json", None)


def estimate(value):
    return {"value": value, "low": value * 0.9, "high": value * 1.1}


def count(streams, a_ms, fps, outcome="holds", dropped=None, server_cores=None):
    """A count of run_capacity's document (the real test checks that the shape is the product's)."""
    stages = {s: {"delay": a_ms * share, "service": a_ms * share * 0.8, "wait": a_ms * share * 0.2,
                  "utilization": share / 2} for s, share in zip(STAGES, (0.5, 0.3, 0.1, 0.05, 0.05))}
    neck = {"stage": "infer", "utilization": 0.9, "thread_utilization": 0.95, "saturated": outcome == "fails"}
    return {"streams": streams, "error": None, "cpu_cores": 1.5, "server_cores": server_cores, "outcome": outcome,
            "checks": [], "limiting": neck, "rate_fps": 30.0,
            "figures": {"streams": streams, "frames": 100, "fps": estimate(fps), "fps_mean": fps,
                        "e2e": {"mean": estimate(a_ms), "p95": estimate(a_ms * 1.5)}, "stages": stages,
                        "between_ms": 0.0, "limiting": neck, "dropped": dropped or {}, "delivered": 200 * streams}}


def doc(*counts, answer="capacity 1 stream"):
    return {"plan": {}, "counts": list(counts), "answer": answer}


def test_markdown_has_one_table_per_bitrate_a_column_per_kind_and_rate_and_the_per_stage_rows():
    docs = {("file", 30, 3982): doc(count(1, 40.0, 30.0), count(2, 90.0, 15.0, "fails")),
            ("rtsp-late", 30, 3982): doc(count(1, 120.0, 29.0, "undecided", {"late": 30}, server_cores=0.45)),
            ("file", 30, 7955): doc(count(1, 44.0, 30.0))}
    text = markdown(docs, "ssd", ["- machine: test"])
    assert text.startswith("- machine: test\n")
    assert "3982 kbit/s (paper's Table 4), model ssd" in text and "7955 kbit/s (paper's Table 6)" in text
    assert "| streams | file 30 fps | rtsp-late 30 fps |" in text
    assert "| 1 | 40.0 (p95 60) @ 30.0 | 120.0 (p95 180) @ 29.0? |" in text
    assert "| 2 | 90.0 (p95 135) @ 15.0* | – |" in text
    assert ("| file | 30 | 3982 | 2 | infer 90%, thread 95% sat. | 36.0/9.0 | 21.6/5.4 | 7.2/1.8 | 3.6/0.9 | 3.6/0.9 "
            "| 0.0 | 90.0 | 135.0 | 15.0* | 0 | 1.50 | – |") in text
    assert "| rtsp-late | 30 | 3982 | 1 | infer 90%, thread 95% | " in text and "| late 30 (30, 15%) | 1.50 | 0.45 |" in text
    rows = [line.split(" | ")[:3] for line in text.splitlines() if line.startswith(("| file |", "| rtsp-late |"))]
    assert rows == [["| file", "30", "3982"]] * 2 + [["| file", "30", "7955"], ["| rtsp-late", "30", "3982"]]
    assert "- file 30 fps 3982 kbit/s: capacity 1 stream" in text


def test_markdown_gives_each_figure_a_count_could_not_produce_as_n_a_with_its_reason():
    failed = {"streams": 2, "error": "the run ended with status 1: boom", "outcome": "fails", "figures": None,
              "limiting": None, "checks": [], "cpu_cores": None, "server_cores": None}
    partial = count(1, 40.0, 30.0)
    partial["figures"]["e2e"].pop("p95")
    partial["figures"]["stages"].pop("osd")
    partial["limiting"] = None
    text = markdown({("file", 30, 3982): doc(partial, failed, answer=None)}, "ssd")
    assert "| 1 | 40.0 (p95 n/a [1]) @ 30.0 |" in text and "| 2 | n/a [2] |" in text
    assert "| file | 30 | 3982 | 1 | n/a [4] | 16.0/4.0 | 9.6/2.4 | 3.2/0.8 | 1.6/0.4 | n/a [3] | 0.0 | 40.0 | n/a [1] |" in text
    notes = text.split("Notes:\n", 1)[1].splitlines()
    assert notes == ["- n/a [1]: no p95 of the frame delay", "- n/a [2]: the run ended with status 1: boom",
                     "- n/a [3]: no frame passed osd after the warm-up",
                     "- n/a [4]: no stage had a delay after the warm-up: no limiting stage",
                     "- file 30 fps 3982 kbit/s 2 stream(s): the run ended with status 1: boom"]
    assert_every_na_has_a_reason(text)


def test_a_clip_that_cannot_be_made_stops_the_sweep_with_one_line(tmp_path, capsys):
    (tmp_path / "cache").write_text("a file, not a folder")
    status = run(lambda: main(["--quick", "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "o.md")]),
                 "streams_sweep.py")
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 2 and err[0].startswith("sweep [")  # "making the clip ...", then the reason
    assert err[1].startswith("streams_sweep.py: cannot run: cannot make the clip vtest_1080p30_3982k_10s_superfast.mp4")


def shape(x):
    """The keys of a document, nested (lists by their first item)."""
    if isinstance(x, dict):
        return {k: shape(v) for k, v in x.items() if k not in ("stages", "dropped", "e2e", "fps")}
    return shape(x[0]) if isinstance(x, list) and x else None


def contains(big, small) -> bool:
    return all(k in big and (not isinstance(v, dict) or contains(big[k] or {}, v)) for k, v in small.items())


@pytest.mark.alone  # a live 30 fps RTSP camera: on a loaded machine few frames come through it
def test_smallest_real_sweep_makes_a_clip_runs_capacity_on_file_and_rtsp_and_reports(tmp_path):
    cache, out = tmp_path / "clips", tmp_path / "sweep.md"
    proc = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "streams_sweep.py"), "--model", "ssd", "--bitrates", "3982",
         "--rates", "30", "--max-streams", "1", "--duration", "1.5", "--warmup", "0.3", "--clip-seconds", "2",
         "--size", "320x180", "--cache", str(cache), "--out", str(out)],
        cwd=tmp_path, env=cli_env(), capture_output=True, text=True, timeout=150)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "making the clip vtest_180p30_3982k_2s_superfast.mp4" in proc.stderr
    assert "capacity [" in proc.stderr  # capacity's progress passed through
    spec = ClipSpec("vtest.avi", 30, 3982, 2, width=320, height=180)
    clip = cache / spec.name
    video = cv2.VideoCapture(str(clip))
    assert (video.get(cv2.CAP_PROP_FRAME_WIDTH), video.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (320, 180)
    assert video.get(cv2.CAP_PROP_FPS) == 30 and 55 <= video.get(cv2.CAP_PROP_FRAME_COUNT) <= 65
    video.release()
    made = clip.stat().st_mtime_ns
    assert make_clip(spec, cache) == clip and clip.stat().st_mtime_ns == made

    docs = {kind: json.loads((tmp_path / f"sweep-{kind}-30-3982.json").read_text()) for kind in ("file", "rtsp")}
    assert docs["file"]["plan"]["rtsp"] is False and docs["rtsp"]["plan"]["rtsp"] is True
    for kind, d in docs.items():
        (c,) = d["counts"]
        assert c["error"] is None and c["figures"]["fps_mean"] > 1 and set(c["figures"]["stages"]) == set(STAGES), c
        assert contains(c, shape(count(1, 1.0, 1.0))), (kind, shape(c))  # the hand-made documents' shape is the product's
    assert 0.05 < docs["rtsp"]["counts"][0]["server_cores"] < 4 and docs["file"]["counts"][0]["server_cores"] is None
    text = out.read_text()
    assert text in proc.stdout and "3982 kbit/s (paper's Table 4), model ssd" in text
    assert "| streams | file 30 fps | rtsp 30 fps |" in text
    a = {kind: d["counts"][0]["figures"]["e2e"]["mean"]["value"] for kind, d in docs.items()}
    assert f"| 1 | {a['file']:.1f} (p95 " in text and "| rtsp | 30 | 3982 | 1 | infer " in text
    assert_every_na_has_a_reason(text)


def test_delaybridge_on_an_interface_it_cannot_open_says_so_in_one_line():
    done = run_benchmark("delaybridge.py", "nosuchif0", "nosuchif1")
    assert_cannot_run(done, "delaybridge.py", "cannot open a packet socket on nosuchif0: ")
