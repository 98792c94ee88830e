"""Configuration checking: every bad input is one line naming file:line and key path, exit 2."""

from __future__ import annotations

import dataclasses
import textwrap
from pathlib import Path

import pytest

from dcuscope.cli import build_parser
from dcuscope.commands.configs import configs_command
from dcuscope.commands.runpipeline import apply_overrides
from dcuscope.core.errors import ConfigError, UsageError
from dcuscope.core.gst import Gst
from dcuscope.pipeline.build import build_pipeline
from dcuscope.pipeline.config import load_config
from dcuscope.pipeline.launch import build_launch
from dcuscope.shipped import CONFIGS, resolve, summary
from tests.conftest import VTEST, run_cli

GOOD = f"""\
node: DCU-7
sources:
  - uri: {VTEST}
    loop: true
    rate: 5
  - test: ball
    live: true
    width: 320
    height: 240
    stall-timeout: 1.5
  - uri: rtsp://127.0.0.1:8554/cam0
    latency: 200
  - uri: {VTEST}
    live: true
stages:
  - mux: {{batch-size: 2, width: 320, height: 240}}
  - infer: {{threshold: 0.4}}
  - factory: identity
    name: slow
    properties: {{sleep-time: 1000}}
  - queue: {{}}
  - queue: {{}}
sink: {{type: fake, sync: false}}
probes: {{enabled: true, clock: tai}}
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "pipeline.yaml"
    path.write_text(textwrap.dedent(text))
    return path


def test_good_config_is_typed(tmp_path):
    cfg = load_config(write(tmp_path, GOOD))
    assert cfg.node == "DCU-7"
    assert [s.kind for s in cfg.sources] == ["uri", "test", "uri", "uri"]
    assert [s.is_live for s in cfg.sources] == [False, True, True, True]
    assert cfg.sources[1].stall_timeout == 1.5 and cfg.sources[0].stall_timeout == 3.0
    assert cfg.sources[2].latency_ms == 200 and cfg.sources[0].latency_ms is None
    assert cfg.sources[0].location == VTEST.as_uri() and cfg.sources[0].loop
    assert cfg.sources[0].rate == 5 and cfg.sources[1].live and cfg.sources[1].width == 320
    assert [s.name for s in cfg.stages] == ["mux", "infer", "slow", "queue", "queue_1"]
    assert cfg.stages[2].factory == "identity" and cfg.stages[2].properties == {"sleep-time": 1000}
    assert cfg.probes.enabled and cfg.probes.clock == "tai"


def test_relative_paths_are_relative_to_the_config(tmp_path):
    (tmp_path / "clips").mkdir()
    clip = tmp_path / "clips" / "a.avi"
    clip.write_bytes(VTEST.read_bytes()[:1000])
    cfg = load_config(write(tmp_path, "sources: [{uri: clips/a.avi}]\nstages: [{queue: {}}]\n"))
    assert cfg.sources[0].location == clip.resolve().as_uri()


BAD = [
    ("malformed yaml", "sources: [\n  - test: ball\nstages: {", ":2: malformed YAML"),
    ("unknown top key", "sources: [{test: ball}]\nstages: [{queue: {}}]\nsinc: {}\n", ":3: sinc: unknown key"),
    ("unknown source key", "sources:\n  - test: ball\n    colour: red\nstages: [{queue: {}}]\n",
     ":3: sources[0].colour: unknown key"),
    ("two kinds", "sources:\n  - test: ball\n    uri: x.mp4\nstages: [{queue: {}}]\n", ":2: sources[0]: a source needs exactly one"),
    ("missing file", "sources:\n  - uri: nothere.mp4\nstages: [{queue: {}}]\n", ":2: sources[0].uri: video file not found"),
    ("missing camera", "sources:\n  - camera: /dev/video99\nstages: [{queue: {}}]\n", ":2: sources[0].camera: camera device not found"),
    ("bad rate", "sources:\n  - test: ball\n    rate: fast\nstages: [{queue: {}}]\n", ":3: sources[0].rate: expected frames per second"),
    ("loop a stream", "sources:\n  - uri: rtsp://127.0.0.1:1/x\n    loop: true\nstages: [{queue: {}}]\n",
     ":3: sources[0].loop: only files can loop"),
    ("live stream", "sources:\n  - uri: rtsp://127.0.0.1:1/x\n    live: true\nstages: [{queue: {}}]\n",
     ":3: sources[0].live: only files and test sources take live: (cameras and streams are live)"),
    ("latency on a file", f"sources:\n  - uri: {VTEST}\n    latency: 100\nstages: [{{queue: {{}}}}]\n",
     ":3: sources[0].latency: only rtsp:// and rtp: sources take latency:"),
    ("negative latency", "sources:\n  - uri: rtsp://127.0.0.1:1/x\n    latency: -1\nstages: [{queue: {}}]\n",
     ":3: sources[0].latency: expected an integer >= 0, got a number (-1)"),
    ("bad stall timeout", "sources:\n  - test: ball\n    stall-timeout: soon\nstages: [{queue: {}}]\n",
     ":3: sources[0].stall-timeout: expected seconds >= 0 (0: off), got text ('soon')"),
    ("unknown stage kind", "sources: [{test: ball}]\nstages:\n  - mixer: {}\n", ":3: stages[0].mixer: unknown stage kind"),
    ("unknown element", "sources: [{test: ball}]\nstages:\n  - factory: nosuchelement\n",
     ":3: stages[0].factory: no GStreamer element named 'nosuchelement'"),
    ("unknown property", "sources: [{test: ball}]\nstages:\n  - mux:\n      batch-sise: 2\n",
     ":4: stages[0].mux.batch-sise: unknown property of mux"),
    ("inserted element property", "sources: [{test: ball}]\nstages:\n  - factory: identity\n    properties: {sleep-tim: 1}\n",
     ":4: stages[0].properties.sleep-tim: unknown property of identity"),
    ("wrong type", "sources: [{test: ball}]\nstages:\n  - mux: {batch-size: two}\n",
     ":3: stages[0].mux.batch-size: expected an integer, got 'two'"),
    ("out of range", "sources: [{test: ball}]\nstages:\n  - infer: {threshold: 7}\n",
     ":3: stages[0].infer.threshold: 7 is out of range"),
    ("bad bool", "sources: [{test: ball}]\nstages:\n  - osd: {display-clock: 3}\n",
     ":3: stages[0].osd.display-clock: expected true or false"),
    ("missing model", "sources: [{test: ball}]\nstages:\n  - infer: {model: nothere.onnx}\n",
     ":3: stages[0].infer.model: file not found"),
    ("bad sink", "sources: [{test: ball}]\nstages: [{queue: {}}]\nsink: {type: screen}\n",
     ":3: sink.type: unknown sink type 'screen'"),
    ("sink in a missing folder", "sources: [{test: ball}]\nstages: [{queue: {}}]\nsink: {type: file, path: /nonexistent/x.mp4}\n",
     ":3: sink.path: /nonexistent/x.mp4: folder /nonexistent does not exist"),
    ("sink container", "sources: [{test: ball}]\nstages: [{queue: {}}]\nsink:\n  type: file\n  path: x.webm\n",
     "x.webm: unknown video container '.webm'"),
    ("model of another decoder", "sources: [{test: ball}]\nstages:\n  - infer: {decoder: ssd}\n",
     ":3: stages[0].infer.decoder: model file"),
    ("sink without path", "sources: [{test: ball}]\nstages: [{queue: {}}]\nsink: {type: file}\n",
     ":3: sink: sink type file needs a path"),
    ("no mux for many", "sources: [{test: ball}, {test: snow}]\nstages: [{queue: {}}]\n",
     ":2: stages[0]: with several sources the first stage must be a mux"),
    ("bad enum", "sources: [{test: ball}]\nstages:\n  - factory: queue\n    properties: {leaky: sideways}\n",
     ":4: stages[0].properties.leaky: expected one of: no, upstream, downstream"),
    # Checked before running: each of these used to start the pipeline (and fail, or run with another value).
    ("our text enum", "sources: [{test: ball}]\nstages:\n  - convert: {format: RGBX2}\n",
     ":3: stages[0].convert.format: expected one of: RGB, BGR, RGBA, BGRA, RGBx, BGRx, I420, NV12, GRAY8; got 'RGBX2'"),
    ("test pattern", "sources:\n  - test: bogus\nstages: [{queue: {}}]\n",
     ":2: sources[0].test: expected one of: smpte, snow, black,"),
    ("bitrate out of x264enc's range", "sources: [{test: ball}]\nstages: [{queue: {}}]\n"
     "sink:\n  type: file\n  path: out.mp4\n  bitrate: 9999999\n", ":6: sink.bitrate: 9999999 is out of range [1, 2048000]"),
]


@pytest.mark.parametrize("name,text,expected", BAD, ids=[b[0] for b in BAD])
def test_bad_config_exits_2_with_one_line(tmp_path, name, text, expected):
    path = write(tmp_path, text)
    result = run_cli("run", path, "--num-frames", "1", cwd=tmp_path, timeout=60)
    assert result.returncode == 2, result.stderr
    lines = [l for l in result.stderr.splitlines() if l.strip() and "CRITICAL" not in l]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"dcuscope: error: {path}"), lines[0]
    assert expected in lines[0], lines[0]
    assert "Traceback" not in result.stderr


def test_a_model_file_that_is_not_onnx_exits_2_naming_file_and_key(tmp_path):
    (tmp_path / "notes.onnx").write_text("not a model\n")
    path = write(tmp_path, "sources: [{test: ball}]\nstages:\n  - infer:\n      model: notes.onnx\n")
    result = run_cli("run", path, "--num-frames", "1", cwd=tmp_path, timeout=60)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"dcuscope: error: {path}:4: stages[0].infer.model: "), lines
    assert f"{tmp_path / 'notes.onnx'} is not a usable ONNX model" in lines[0]


def test_missing_config_file(tmp_path):
    result = run_cli("run", tmp_path / "nope.yaml", cwd=tmp_path, timeout=60)
    assert result.returncode == 2
    assert "no such configuration file" in result.stderr and "Traceback" not in result.stderr


def test_loading_reports_the_key_path_in_python(tmp_path):
    with pytest.raises(ConfigError, match=r"pipeline.yaml:3: sources\[0\]\.rate"):
        load_config(write(tmp_path, "sources:\n  - test: ball\n    rate: 0\nstages: [{queue: {}}]\n"))


def test_a_checked_config_cannot_be_changed(tmp_path):
    cfg = load_config(write(tmp_path, GOOD))
    for obj, field, value in [(cfg, "node", "x"), (cfg.sources[0], "width", 1), (cfg.stages[0], "name", "x"),
                              (cfg.sink, "path", tmp_path), (cfg.probes, "enabled", False)]:
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, field, value)
    with pytest.raises(TypeError):
        cfg.stages[1].properties["threshold"] = 0.9
    with pytest.raises(AttributeError):
        cfg.sources.append(cfg.sources[0])


def test_a_stage_name_is_not_taken_out_of_the_yaml_data(tmp_path):
    cfg = load_config(write(tmp_path, "sources: [{test: ball}]\nstages:\n  - queue: {name: q, max-size-buffers: 2}\n"))
    assert cfg.stages[0].name == "q" and dict(cfg.stages[0].properties) == {"max-size-buffers": 2}
    assert cfg.document.data["stages"][0]["queue"] == {"name": "q", "max-size-buffers": 2}


def test_building_and_overrides_leave_the_config_as_it_was(tmp_path, gst_registered):
    cfg = load_config(write(tmp_path, "sources:\n  - {test: ball}\n  - {test: snow, width: 64, height: 48}\n"
                                      "stages:\n  - mux: {width: 320, height: 240}\n"))
    before = repr(cfg)
    built = build_pipeline(cfg)
    assert built.scaled_to == [(320, 240), (64, 48)]  # what the build resolved, returned
    assert (cfg.sources[0].width, cfg.sources[0].height) == (None, None)
    args = build_parser().parse_args(["run", "x.yaml", "--node", "N", "--probes", "--clock", "tai",
                                      "--output", str(tmp_path / "out.mp4")])
    new = apply_overrides(cfg, args)
    assert (new.node, new.probes.enabled, new.probes.clock, new.sink.kind) == ("N", True, "tai", "file")
    assert repr(cfg) == before


def test_max_latency_reaches_the_mux_which_ages_frames_on_the_probes_clock(tmp_path, gst_registered):
    cfg = load_config(write(tmp_path, "sources: [{test: ball}]\nstages:\n  - mux: {max-latency: 150}\n"
                                      "probes: {clock: tai}\n"))
    built = build_pipeline(cfg)
    mux, stamp = built.stages[0], built.sources[0].stamp
    assert mux.get_property("max-latency") == 150
    assert mux.get_property("clock-id") == stamp.get_property("clock-id") == 11


@pytest.mark.parametrize("stage,expected", [
    ("factory: identity\n    properties: {drop-buffer-flags: live+bogus}",
     ":4: stages[0].properties.drop-buffer-flags: unknown flag 'bogus': expected flags from: live, decode-only, "),
    ("factory: capsfilter\n    properties: {caps: 'video/x-raw,format={RGB,RGBX2}'}",
     ":4: stages[0].properties.caps: unknown video format 'RGBX2' (known: I420, YV12, "),
    ("infer: {decoder: yolo9}", ":3: stages[0].infer.decoder: expected one of: auto, centernet, ssd, yolo; got 'yolo9'"),
], ids=["flags", "caps format", "infer decoder"])
def test_values_are_checked_against_what_the_element_knows(tmp_path, gst_registered, stage, expected):
    cfg = load_config(write(tmp_path, f"sources: [{{test: ball}}]\nstages:\n  - {stage}\n"))
    with pytest.raises(ConfigError) as caught:
        build_pipeline(cfg)
    assert expected in str(caught.value), caught.value


def test_good_flags_and_caps_are_set(tmp_path, gst_registered):
    cfg = load_config(write(tmp_path, "sources: [{test: ball}]\nstages:\n"
                                      "  - factory: identity\n    properties: {drop-buffer-flags: [live, discont]}\n"
                                      "  - factory: identity\n    properties: {drop-buffer-flags: 0}\n"
                                      "  - factory: capsfilter\n    properties: {caps: 'video/x-raw,format={RGB,NV12}'}\n"))
    first, second, caps = build_pipeline(cfg).stages
    assert int(first.get_property("drop-buffer-flags")) == int(Gst.BufferFlags.LIVE | Gst.BufferFlags.DISCONT)
    assert int(second.get_property("drop-buffer-flags")) == 0  # refused before: it equals the default
    assert caps.get_property("caps").get_structure(0).get_value("format").array == ["RGB", "NV12"]


def test_a_launch_line_checks_our_text_enums_before_running(tmp_path, gst_registered):
    cfg = load_config(write(tmp_path, "launch: videotestsrc num-buffers=1 ! convert name=c format=RGBX2 ! fakesink\n"))
    with pytest.raises(ConfigError, match=r"pipeline.yaml:1: launch: c.format: expected one of: RGB, .*; got 'RGBX2'"):
        build_launch(cfg)


def test_configs_lists_whole_sentences(tmp_path, capsys):
    (tmp_path / "x.yaml").write_text("# Two cameras, batched: the mux waits for both, e.g. after a stall. Then more\n"
                                     "# text that is not the first sentence.\n#   dcuscope run x.yaml\nnode: X\n")
    assert summary(tmp_path / "x.yaml") == "Two cameras, batched: the mux waits for both, e.g. after a stall."
    configs_command(build_parser().parse_args(["configs"]))
    listing = capsys.readouterr().out.split("\n\n")[0]
    entries = [line for line in listing.splitlines() if not line.startswith(" ")]
    assert len(entries) == len(list(CONFIGS.glob("*.yaml")))
    for entry in listing.replace("\n ", " ").splitlines():  # the wrapped lines joined again
        assert entry.rstrip().endswith((".", "!", "?")), entry


def test_a_shipped_configs_path_outside_a_checkout_suggests_its_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UsageError, match=r"^configs/quad.yaml: no such configuration file; .*: dcuscope run quad$"):
        resolve(Path("configs/quad.yaml"))
    assert resolve(Path("elsewhere/x.yaml")) == Path("elsewhere/x.yaml")  # load_config says it is missing
