"""``dcuscope demo``: a relay and two DCU pipelines with probes on the shipped clips.

DCU-1 runs two cameras through CenterNet, DCU-2 four cameras through the SSD person detector,
both paced in real time and streaming their probe events to a relay on loopback, whose UI
shows where the time goes. Runs until Ctrl-C (or ``--duration``), then stops the pipelines
with end-of-stream and the relay, in that order.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from pipeline.errors import PipelineError

ROOT = Path(__file__).resolve().parents[1]
NODES = (("DCU-1", ROOT / "configs" / "demo-dcu1.yaml"), ("DCU-2", ROOT / "configs" / "demo-dcu2.yaml"))
STATUS_EVERY_S = 5.0


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "pipeline.cli", *args]


def _get_json(url: str, timeout: float = 2.0):
    with urllib.request.urlopen(url, timeout=timeout) as response:
        return json.loads(response.read())


def _wait_for_relay(url: str, relay: subprocess.Popen, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if relay.poll() is not None:
            raise PipelineError(f"the relay exited at start (status {relay.returncode}); is port taken? see above")
        try:
            _get_json(f"{url}/api/nodes")
            return
        except OSError:
            time.sleep(0.2)
    raise PipelineError(f"the relay did not answer at {url} within {timeout_s:.0f} s")


def _status_line(url: str) -> str:
    try:
        nodes = _get_json(f"{url}/api/nodes")
    except OSError as exc:
        return f"relay unreachable: {exc}"
    parts = []
    for node in nodes if isinstance(nodes, list) else nodes.get("nodes", []):
        name = node.get("node", "?")
        try:
            stats = _get_json(f"{url}/api/stats?node={name}")
            frame = stats.get("frame", {})
            fps = sum((stats.get("fps") or {}).values())
            mean = frame.get("mean_ms")
            bottleneck = (stats.get("bottleneck") or {}).get("stage") or "-"
            parts.append(f"{name}: {fps:5.1f} fps, frame delay {mean:7.1f} ms, bottleneck {bottleneck}"
                         if mean is not None else f"{name}: waiting for frames")
        except OSError:
            parts.append(f"{name}: no stats yet")
    return " | ".join(parts) or "no node connected yet"


def run_demo(port: int = 3000, duration: float | None = None, db: Path | None = None) -> int:
    url = f"http://127.0.0.1:{port}"
    db = db or Path.cwd() / "dcuscope-demo.db"
    print(f"demo: starting the relay on {url} (sessions stored in {db})", flush=True)
    # Own sessions: the terminal's Ctrl-C reaches only this process, which then stops the
    # pipelines (one SIGINT each: a clean EOS) before the relay.
    relay = subprocess.Popen(_cli("relay", "--port", str(port), "--db", str(db)), start_new_session=True)
    nodes: list[subprocess.Popen] = []
    interrupted = False
    try:
        _wait_for_relay(url, relay)
        for name, config in NODES:
            print(f"demo: starting {name} ({config.relative_to(ROOT)}) with probes -> {url}", flush=True)
            nodes.append(subprocess.Popen(_cli("run", str(config), "--probes", "--relay", url, "--node", name, "-q"),
                                          stdout=subprocess.DEVNULL, start_new_session=True))
        print(f"\n  open {url}/ in a browser to watch the DCUs live. Ctrl-C stops the demo.\n", flush=True)
        started = time.monotonic()
        last_status = started
        while duration is None or time.monotonic() - started < duration:
            time.sleep(0.5)
            if any(n.poll() is not None for n in nodes) or relay.poll() is not None:
                raise PipelineError("a demo process exited early (see its message above)")
            if time.monotonic() - last_status >= STATUS_EVERY_S:
                last_status = time.monotonic()
                print(f"demo: {_status_line(url)}", flush=True)
    except KeyboardInterrupt:
        interrupted = True
        print("\ndemo: stopping", flush=True)
    finally:
        _stop_all(nodes, relay)
    return 130 if interrupted else 0


def _stop_all(nodes: list[subprocess.Popen], relay: subprocess.Popen) -> None:
    """Pipelines first (EOS, so their last events reach the relay), then the relay."""
    for proc in nodes:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    for proc in nodes:
        _wait(proc, 30)
    if relay.poll() is None:
        relay.send_signal(signal.SIGINT)
    _wait(relay, 15)
    print("demo: stopped", flush=True)


def _wait(proc: subprocess.Popen, timeout: float) -> None:
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
