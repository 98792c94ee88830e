"""Live RTSP streams served on loopback by dcuscope serve-rtsp, processed end to end with probes."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import numpy as np

from probes.events import ORIGIN
from probes.stats import chains, frame_table
from probes.tracefile import read_trace
from tests.conftest import BIKES, VTEST, cli_env


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve(*clips, port: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "serve-rtsp", *map(str, clips), "--port", str(port)],
                            env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert f"rtsp://127.0.0.1:{port}/cam0" in proc.stdout.readline()
    return proc


def run(config, trace, duration, cwd) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "pipeline.cli", "run", str(config), "--probes", "--trace", str(trace),
                             "--duration", str(duration)], cwd=cwd, env=cli_env(), stderr=subprocess.PIPE, text=True)


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


def test_killing_the_rtsp_server_leaves_the_other_source_running_and_reports_the_loss(tmp_path):
    port = free_port()
    server = serve(VTEST, port=port)
    config = tmp_path / "mixed.yaml"
    config.write_text(
        f"sources:\n  - uri: rtsp://127.0.0.1:{port}/cam0\n  - {{test: ball, live: true, rate: 10}}\n"
        "stages:\n  - mux: {batch-size: 2, width: 320, height: 240, live-source: true}\n  - queue: {}\n"
    )
    node = run(config, tmp_path / "t.jsonl", 14, tmp_path)
    time.sleep(5)
    server.kill()
    killed_at = time.time_ns()
    server.wait(10)
    _, stderr = node.communicate(timeout=60)
    assert node.returncode == 0, stderr
    assert "source 0 (uri:rtsp://" in stderr and "was lost" in stderr and "Traceback" not in stderr
    events = read_trace(tmp_path / "t.jsonl").events
    origins = events[events["point"] == ORIGIN]
    before = origins[origins["ts"] < killed_at]
    after = origins[origins["ts"] > killed_at + 2_000_000_000]
    assert (before["source"] == 0).sum() >= 10  # the stream was flowing before the kill
    assert (after["source"] == 0).sum() == 0 and (after["source"] == 1).sum() >= 40  # the test source went on
