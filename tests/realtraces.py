"""Two real traces, made once per worker (``real_traces``, a session fixture of tests/conftest.py): an
unchanged gst-launch app through a tee (GStreamer's tracer, its graph), and a dcuscope pipeline whose
mux batches two live-rate cameras (service and wait times, groups)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

TWO_CAMERAS = """node: CAM-2
sources:
  - {test: ball, width: 160, height: 120, rate: 30}
  - {test: smpte, width: 160, height: 120, rate: 30}
stages:
  - mux: {batch-size: 2, width: 160, height: 120}
  - tiler: {rows: 1, columns: 2, width: 320, height: 120}
  - convert: {}
"""
COMMANDS = {
    "tee": ["trace", "--node", "CAM-1", "-o", "tee.jsonl", "--", "gst-launch-1.0", "-q", "videotestsrc", "num-buffers=150",
            "!", "video/x-raw,width=160,height=120", "!", "tee", "name=t", "!", "queue", "!", "videoconvert", "!",
            "fakesink", "t.", "!", "queue", "!", "fakesink"],
    "two": ["run", "two.yaml", "--probes", "--trace", "two.jsonl", "-n", "120", "-q"],
}


def make(folder: Path, env: dict) -> dict:
    """name -> the trace (``read_trace``) of each of :data:`COMMANDS`, run in ``folder``."""
    from dcuscope.probes.trace.tracefile import read_trace

    (folder / "two.yaml").write_text(TWO_CAMERAS)
    traces = {}
    for name, args in COMMANDS.items():
        done = subprocess.run([sys.executable, "-m", "dcuscope.cli", *args], cwd=folder, env=env,
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr[-3000:]
        traces[name] = read_trace(folder / f"{name}.jsonl")
    return traces
