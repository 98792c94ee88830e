"""A dcuscope config declares both ends of a link: an ``rtp``/``shm`` sink sends its frames to another
pipeline, an ``rtp:``/``shm:`` source takes them. Three real ``dcuscope run --probes`` processes (one
sender with both sinks, a receiver of each), and their traces joined by ``dcuscope stats``."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time

import pytest

from dcuscope.core.errors import ConfigError
from dcuscope.pipeline.config import load_config
from tests.conftest import cli_env, run_cli

pytestmark = pytest.mark.long

STAGES = """stages:
  - mux: {batch-size: 1, width: 320, height: 240}
  - tiler: {rows: 1, columns: 1, width: 320, height: 240}
  - convert: {}
"""


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(tmp, name: str, text: str, seconds: float) -> subprocess.Popen:
    (tmp / f"{name}.yaml").write_text(text)
    return subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", f"{name}.yaml", "--probes", "--trace",
                             f"{name}.jsonl", "--duration", str(seconds), "-q"], cwd=tmp, env=cli_env(),
                            stderr=subprocess.PIPE, text=True)


@pytest.fixture(scope="module")
def journeys(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ends")
    port = free_udp_port()
    # Each end outlives what it feeds: the sender runs until the shm viewer is done, the RTP receiver
    # until the sender is, each then stopped by Ctrl-C as a user stops it. On a loaded machine the
    # viewer may start late, and a sender gone before it took its frames closes its socket.
    receiver = run(tmp, "DCU-2", f"node: DCU-2\nsources:\n  - {{rtp: {port}, latency: 100}}\n{STAGES}sink: {{type: fake}}\n",
                   90)
    time.sleep(1.0)
    sender = run(tmp, "DCU-1", "node: DCU-1\nsources:\n  - {test: ball, live: true, width: 320, height: 240, rate: 25}\n"
                 f"{STAGES}sinks:\n  - {{type: rtp, port: {port}}}\n  - {{type: shm, path: frames.sock}}\n", 90)
    time.sleep(1.5)  # the socket is there
    viewer = run(tmp, "DCU-3", "node: DCU-3\nsources:\n  - {shm: frames.sock, width: 320, height: 240, rate: 25}\n"
                 f"{STAGES}sink: {{type: fake}}\n", 3)
    for proc, name, after_s in ((viewer, "DCU-3", None), (sender, "DCU-1", 0.0), (receiver, "DCU-2", 1.0)):
        if after_s is not None:
            time.sleep(after_s)  # the receiver: the sender's last packets are in
            proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=90)
        assert proc.returncode == 0, (name, err)
    result = run_cli("stats", *(tmp / f"DCU-{i}.jsonl" for i in (1, 2, 3)), "--json", cwd=tmp)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_an_rtp_sink_and_an_rtp_source_are_the_two_ends_of_a_hop(journeys):
    j = journeys["journeys"]
    hop = j["hops"]["net DCU-1 → DCU-2"]
    assert hop["count"] >= 50 and hop["lost"] == 0
    path = j["paths"]["DCU-1 → DCU-2"]
    assert list(path["parts"]) == ["DCU-1", "net DCU-1 → DCU-2", "DCU-2"] and path["count"] >= 50


def test_a_shm_sink_and_a_shm_source_are_the_two_ends_of_a_hop(journeys):
    j = journeys["journeys"]
    hop = j["hops"]["shm DCU-1 → DCU-3"]
    viewer = journeys["nodes"]["DCU-3"]["frames"]
    # Every frame the viewer made (it joined late and left early) is one the sender sent.
    assert hop["count"] >= 30 and hop["count"] == viewer["complete"] + viewer["incomplete"]
    assert "DCU-3" not in j["untraced"] and "DCU-3" not in j["ambiguous"]


@pytest.mark.parametrize("source, says", [
    ("{rtp: 5600, encoding: VP9}", "sources[0].encoding: expected one of: H264, H265, JPEG"),
    ("{rtp: 70000}", "sources[0].rtp: expected the UDP port RTP arrives on, 1..65535, got 70000"),
    ("{shm: x.sock, width: 320}", "sources[0]: a shm: source needs the sender's height, rate"),
    ("{test: ball, encoding: H264}", "sources[0].encoding: only rtp: sources take encoding:"),
    ("{rtp: 5600, live: true}", "sources[0].live: only files and test sources take live:"),
])
def test_a_bad_link_source_is_named(tmp_path, source, says):
    path = tmp_path / "p.yaml"
    path.write_text(f"sources:\n  - {source}\n{STAGES}")
    with pytest.raises(ConfigError, match=says.replace("[", r"\[").replace("]", r"\]").replace("(", r"\(")):
        load_config(path)


@pytest.mark.parametrize("sink, says", [
    ("{type: rtp}", "sink: sink type rtp needs the port: it sends to"),
    ("{type: shm}", "sink: sink type shm needs a path: (the socket shmsrc connects to)"),
    ("{type: rtp, port: 5600, mount: /x}", "sink.mount: only rtsp sinks take mount:"),
    ("{type: fake, port: 5600}", "sink.port: only rtsp and rtp sinks take port:"),
])
def test_a_bad_link_sink_is_named(tmp_path, sink, says):
    path = tmp_path / "p.yaml"
    path.write_text(f"sources:\n  - {{test: ball}}\n{STAGES}sink: {sink}\n")
    with pytest.raises(ConfigError, match=says.replace("(", r"\(").replace(")", r"\)")):
        load_config(path)


def test_a_shm_sink_whose_socket_exists_is_refused_before_it_runs(tmp_path):
    (tmp_path / "frames.sock").write_text("")
    (tmp_path / "p.yaml").write_text(f"sources:\n  - {{test: ball}}\n{STAGES}sink: {{type: shm, path: frames.sock}}\n")
    result = run_cli("run", tmp_path / "p.yaml", "-n", "5", cwd=tmp_path)
    assert result.returncode == 2 and "exists already (another shmsink's socket?" in result.stderr
