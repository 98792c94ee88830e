"""Graphs in our own YAML: several sinks through a tee (a file and an RTSP server at once), and
``launch:`` pipelines in gst-launch syntax; each traced branch by branch."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from dcuscope.core.errors import ConfigError
from dcuscope.pipeline.config import load_config
from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.protocol.events import ENTER, EXIT, ORIGIN
from tests.conftest import REPO, run_cli
from tests.pipeline.clips import decode_video
from tests.relay.helpers import RelayProcess, get_json, wait_for
from tests.ports import free_port


def write(tmp_path: Path, text: str, name: str = "graph.yaml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def frames_at(trace, stage: str, point: int) -> set[tuple[int, int]]:
    ev = trace.events
    ev = ev[(ev["stage"] == trace.header.stages.index(stage)) & (ev["point"] == point)]
    return set(zip(ev["source"].tolist(), ev["frame"].tolist()))


def wait_for_port(port: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise AssertionError(f"nothing listens on port {port} after {timeout} s")


def test_a_file_and_an_rtsp_server_at_once_every_frame_on_both_branches(tmp_path):
    port = free_port()
    config = write(tmp_path, f"""\
        node: TWO
        sources:
          - test: ball
            live: true
            width: 320
            height: 240
        stages:
          - factory: identity
            name: work
            properties: {{sleep-time: 2000}}
        sinks:
          - {{type: file, path: {tmp_path / 'out.mp4'}}}
          - {{type: rtsp, port: {port}, mount: /out}}
        """)
    trace_path = tmp_path / "t.jsonl"
    run = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config), "--probes", "--trace",
                            str(trace_path), "--duration", "10"], cwd=REPO, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    try:
        wait_for_port(port, 30)
        # A client reads the stream back: 30 decoded pictures, then it ends by itself.
        client = subprocess.run(["gst-launch-1.0", "-q", "rtspsrc", f"location=rtsp://127.0.0.1:{port}/out",
                                 "latency=100", "!", "rtph264depay", "!", "avdec_h264", "!", "identity",
                                 "eos-after=30", "!", "fakesink"], capture_output=True, text=True, timeout=40)
        assert client.returncode == 0, client.stderr
        _, err = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, err
    assert f"serving rtsp://127.0.0.1:{port}/out (sink rtsp)" in err

    trace = read_trace(trace_path)
    h = trace.header
    assert h.stages == ["src0", "work", "tee", "file_queue", "file", "rtsp_queue", "rtsp"]
    assert [2, 3] in h.links and [2, 5] in h.links and [3, 4] in h.links and [5, 6] in h.links
    made = frames_at(trace, "src0", ORIGIN)
    assert len(made) >= 150, err  # 10 s at 30 frames/s, less the start
    to_file, to_rtsp = frames_at(trace, "file", ENTER), frames_at(trace, "rtsp", ENTER)
    assert to_file == made, (len(made), len(to_file), sorted(made - to_file)[:5])
    assert to_rtsp == made, (len(made), len(to_rtsp), sorted(made - to_rtsp)[:5])
    # The file holds every frame and plays.
    assert len(decode_video(tmp_path / "out.mp4")) == len(made)
    stats = json.loads(run_cli("stats", trace_path, "--json").stdout)["nodes"]["TWO"]
    assert stats["frames"] == {"complete": len(made), "incomplete": 0}
    assert stats["stages"]["work"]["service"]["p50_ms"] >= 2.0


def test_a_launch_config_with_a_compositor_is_traced_like_any_app(tmp_path):
    """A compositor of a 30 and a 10 frames/s source in a launch: line: each output buffer lists,
    per source, the frame whose time covers it (videotestsrc's frame k starts at k / rate); the
    trace goes to a relay live too."""
    config = write(tmp_path, """\
        node: MIX
        launch: >
          compositor name=mix ! video/x-raw,framerate=30/1 ! videoconvert ! fakesink name=out
          videotestsrc name=a num-buffers=60 ! video/x-raw,width=320,height=240,framerate=30/1 ! mix.sink_0
          videotestsrc name=b num-buffers=20 pattern=ball ! video/x-raw,width=160,height=120,framerate=10/1 ! mix.sink_1
        """)
    relay = RelayProcess(tmp_path / "relay.db")
    try:
        result = run_cli("run", config, "--probes", "--trace", tmp_path / "m.jsonl", "--relay", relay.url, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        assert "(the dcuscope tracer, every element)" in result.stderr
        # Shipped live as the tracer writes it: the relay holds the same frames.
        live = wait_for(lambda: (s := get_json(f"{relay.url}/api/stats?node=MIX"))["frames"]["complete"] == 80 and s,
                        30, 0.2, "the relay's 80 frames of MIX")
        assert live["frames"]["incomplete"] == 0
    finally:
        relay.stop()
    trace = read_trace(tmp_path / "m.jsonl")
    source = {name: int(i) for i, name in trace.header.sources.items()}
    assert set(source) == {"a", "b"}
    ev = trace.events
    exits = ev[(ev["stage"] == trace.header.stages.index("mix")) & (ev["point"] == EXIT)]
    outputs = sorted(set(exits["ts"].tolist()))
    assert len(outputs) == 60
    for ts in outputs:
        listed = {int(s): int(f) for s, f in zip(*(exits[exits["ts"] == ts][c] for c in ("source", "frame")))}
        a = listed[source["a"]]
        assert listed == {source["a"]: a, source["b"]: a // 3}, listed
    stats = json.loads(run_cli("stats", tmp_path / "m.jsonl", "--json").stdout)["nodes"]["MIX"]
    assert stats["frames"] == {"complete": 80, "incomplete": 0}


@pytest.mark.parametrize("body, where, says", [
    ("sink: {type: fake}\nsinks:\n  - {type: fake}\n", "sinks", "either sink: (one output) or sinks:"),
    ("sinks: []\n", "sinks", "at least one sink"),
    ("sinks:\n  - {type: rtsp, port: 9000}\n  - {type: rtsp, port: 9000}\n", "sinks[1].mount", "is served twice"),
    ("sinks:\n  - {type: rtsp, port: 70000}\n", "sinks[0].port", "1..65535"),
    ("sinks:\n  - {type: rtsp, mount: out}\n", "sinks[0].mount", "such as /out"),
    ("sinks:\n  - {type: file, port: 9000, path: x.mp4}\n", "sinks[0].port", "only rtsp and rtp sinks take port:"),
    ("sink: {type: fake, name: x}\n", "sink.name", "names are for sinks: entries"),
])
def test_bad_sinks_are_one_line_naming_the_key(tmp_path, body, where, says):
    config = write(tmp_path, "sources:\n  - test: ball\nstages:\n  - queue: {}\n" + body)
    with pytest.raises(ConfigError) as info:
        load_config(config)
    message = str(info.value)
    assert message.startswith(f"{config}:") and f": {where}: " in message and says in message, message


def test_names_of_several_sinks_are_unique(tmp_path):
    config = load_config(write(tmp_path, "sources:\n  - test: ball\nstages:\n  - queue: {}\nsinks:\n"
                                         "  - {type: fake}\n  - {type: fake}\n  - {type: fake, name: shown}\n"))
    assert [s.name for s in config.sinks] == ["fake", "fake_1", "shown"]


def test_a_taken_rtsp_port_and_a_bad_launch_line_exit_2_with_file_and_line(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        config = write(tmp_path, f"sources:\n  - test: ball\nstages:\n  - queue: {{}}\n"
                                 f"sinks:\n  - {{type: fake}}\n  - {{type: rtsp, port: {port}}}\n")
        result = run_cli("run", config, "--num-frames", "5")
    assert result.returncode == 2
    assert f"{config}:7: sinks[1].port: cannot listen on 127.0.0.1:{port}" in result.stderr
    bad = write(tmp_path, "launch: videotestsrc ! nosuchelement ! fakesink\n", "bad.yaml")
    result = run_cli("run", bad, "--num-frames", "5")
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert f"{bad}:1: launch: GStreamer cannot build it: no element \"nosuchelement\"" in result.stderr
    both = write(tmp_path, "launch: videotestsrc ! fakesink\nsources:\n  - test: ball\n", "both.yaml")
    result = run_cli("run", both, "--num-frames", "5")
    assert result.returncode == 2 and "remove sources: (or launch:)" in result.stderr
