"""``dcuscope demo``: a relay and two DCU pipelines with probes on the shipped clips.

DCU-1 runs two cameras through CenterNet, DCU-2 four cameras through the SSD person detector,
both paced in real time and streaming their probe events to a relay on loopback, whose UI
shows where the time goes. Runs until Ctrl-C, SIGTERM or SIGHUP (or ``--duration``), then stops
the pipelines with end-of-stream and the relay, in that order. Should the demo itself be killed
outright, the kernel sends its children SIGTERM, so no pipeline or relay outlives it.
"""

from __future__ import annotations

import ctypes
import json
import signal
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

from dcuscope.core.datadir import DATA
from dcuscope.core.errors import PipelineError
from dcuscope.core.ports import check_port_free

NODES = (("DCU-1", DATA / "configs" / "demo-dcu1.yaml"), ("DCU-2", DATA / "configs" / "demo-dcu2.yaml"))
STATUS_EVERY_S = 5.0
PR_SET_PDEATHSIG = 1  # linux/prctl.h
NODE_CLOSE_TIMEOUT_S = 10.0
"""How long a stopping pipeline waits for the relay to acknowledge its last events. The relay is the
demo's own, on loopback, and still up while the demo stops its pipelines (it answers within a
second); should the demo be killed, the relay dies with it, and a minute's wait for it (``dcuscope
run``'s default, for relays elsewhere that may come back) would only keep the pipelines running on."""


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class _StopRequest:
    """The first of Ctrl-C, SIGTERM or SIGHUP, noted by the handler and acted on by the demo's
    loops. Not an exception raised wherever the demo happens to be: one raised inside a finalizer
    (a socket of a status request being collected, say) is printed and lost, and the demo then ran on."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def note(self, signum: int, _frame) -> None:
        if self.signum is None:
            self.signum = signum

    def __bool__(self) -> bool:
        return self.signum is not None


def _die_with_parent() -> None:
    """Run in each child before exec: SIGTERM to it when the demo dies, however it dies (Linux)."""
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def _start(*args: str, **popen) -> subprocess.Popen:
    """``dcuscope ARGS`` as a child. In a session of its own, so that the terminal's Ctrl-C reaches
    only the demo, which then stops the pipelines (one SIGINT each: a clean EOS) before the relay;
    and told to end with the demo, should the demo die without stopping it."""
    return subprocess.Popen([sys.executable, "-m", "dcuscope.cli", *args], start_new_session=True,
                            preexec_fn=_die_with_parent, **popen)


def _get_json(url: str, timeout: float = 2.0):
    with urllib.request.urlopen(url, timeout=timeout) as response:
        return json.loads(response.read())


def _wait_for_relay(url: str, relay: subprocess.Popen, stop: _StopRequest, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not stop:
        if relay.poll() is not None:
            raise PipelineError(f"the relay exited at start (status {relay.returncode}); is port taken? see above")
        try:
            _get_json(f"{url}/api/nodes")
            return
        except OSError:
            time.sleep(0.2)
    if not stop:
        raise PipelineError(f"the relay did not answer at {url} within {timeout_s:.0f} s")


def status_lines(url: str, said_ended: set | None = None) -> list[str]:
    """One line per DCU, aligned (two DCUs on one line would run past a terminal's width every 5 s):
    over the relay's rolling window (the last 10 s, as the page's overview), frames/s, mean frame
    delay and verdict; a run that ended says so, once: the (node, run) pairs in ``said_ended`` were said
    (it is added to), and a line would only repeat itself every 5 s for the rest of the demo. One gone
    silent says that no frame came in the window. No line when every DCU listed ended and was said."""
    try:
        nodes = _get_json(f"{url}/api/nodes")
    except OSError as exc:
        return [f"relay unreachable: {exc}"]
    nodes = [n for n in (nodes if isinstance(nodes, list) else nodes.get("nodes", [])) if isinstance(n, dict)]
    said_ended = set() if said_ended is None else said_ended
    width = max((len(n.get("node", "?")) for n in nodes), default=0) + 1
    lines = []
    for node in nodes:
        name = node.get("node", "?")
        head = f"{name + ':':<{width}}"
        shown = (node.get("frames") or {}).get("shown", 0)
        if node.get("ended"):
            if (name, node.get("run")) not in said_ended:
                said_ended.add((name, node.get("run")))
                lines.append(f"{head} ended ({shown:,} frames)")
            continue
        try:
            window = _get_json(f"{url}/api/stats?node={urllib.parse.quote(name)}").get("window") or {}
        except OSError:
            lines.append(f"{head} no stats yet")
            continue
        fps = sum((window.get("fps") or {}).values())
        mean = (window.get("frame") or {}).get("mean_ms")
        if mean is not None:
            lines.append(f"{head} {fps:5.1f} fps, frame delay {mean:7.1f} ms, {_verdict(window.get('bottleneck'))}")
        elif shown:
            lines.append(f"{head} no frame in the last {window.get('window_s', 10):.0f} s ({node.get('state', '?')})")
        else:
            lines.append(f"{head} waiting for frames")
    return lines if lines or nodes else ["no node connected yet"]


def _verdict(b: dict | None) -> str:
    """The bottleneck in a few words: the saturated stage and how busy it is, or that none is."""
    if not b:
        return "bottleneck -"
    busy = f"{b['utilization'] * 100:.0f} % busy" if b.get("utilization") is not None else "largest share"
    if b.get("saturated") is False:
        return f"no stage saturated (busiest {b['stage']} {busy})"
    return f"bottleneck {b['stage']} ({busy})"


def run_demo(port: int = 3000, duration: float | None = None, db: Path | None = None) -> int:
    url = f"http://127.0.0.1:{port}"
    # a relay already on the port would answer for ours and take our DCUs
    check_port_free("127.0.0.1", port, "another demo or relay? pick a free one with --port (make demo PORT=...)")
    db = db or Path.cwd() / "dcuscope-demo.db"
    print(f"demo: starting the relay on {url} (sessions stored in {db})", flush=True)
    relay = _start("relay", "--port", str(port), "--db", str(db))
    nodes: list[subprocess.Popen] = []
    status = 0
    stop = _StopRequest()
    handlers = {sig: signal.signal(sig, stop.note) for sig in STOP_SIGNALS}
    try:
        _wait_for_relay(url, relay, stop)
        for name, config in NODES:
            if stop:
                break
            print(f"demo: starting {name} ({config.relative_to(DATA)}) with probes -> {url}", flush=True)
            # The demo's own spool, beside its database: what a stopped demo left goes to the next demo's
            # relay, never to a real relay that a later `dcuscope run --relay` on this machine ships to.
            nodes.append(_start("run", str(config), "--probes", "--relay", url, "--node", name, "-q",
                                "--close-timeout", str(NODE_CLOSE_TIMEOUT_S), "--spool", str(db.with_suffix(".spool")),
                                stdout=subprocess.DEVNULL))
        if not stop:
            print(f"\n  open {url}/ in a browser to watch the DCUs live. Ctrl-C stops the demo.\n", flush=True)
        started = time.monotonic()
        last_status = started
        said_ended: set = set()
        while not stop and (duration is None or time.monotonic() - started < duration):
            time.sleep(0.5)
            if any(n.poll() is not None for n in nodes) or relay.poll() is not None:
                raise PipelineError("a demo process exited early (see its message above)")
            if time.monotonic() - last_status >= STATUS_EVERY_S:
                last_status = time.monotonic()
                lines = status_lines(url, said_ended)
                if lines:
                    print("\n".join(f"demo: {line}" for line in lines), flush=True)
        if stop:
            status = 128 + stop.signum
            said = "" if stop.signum == signal.SIGINT else f" {signal.Signals(stop.signum).name} received,"
            print(f"\ndemo:{said} stopping", flush=True)
    finally:
        for sig, handler in handlers.items():  # a second signal while stopping ends the demo at once
            signal.signal(sig, handler)
        _stop_all(nodes, relay)
    return status


def _stop_all(nodes: list[subprocess.Popen], relay: subprocess.Popen) -> None:
    """Pipelines first (EOS, so their last events reach the relay), then the relay.

    SIGTERM, not SIGINT: a child that is still importing, before its handlers are in place,
    then ends silently (nothing of it has started yet), where SIGINT would print a
    KeyboardInterrupt traceback from the middle of an import."""
    for proc in nodes:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    for proc in nodes:
        _wait(proc, 30)
    from dcuscope.relay.store.compactor import STOP_ROLLUP_S

    if relay.poll() is None:
        relay.send_signal(signal.SIGTERM)
    _wait(relay, 15 + STOP_ROLLUP_S)  # it rolls up its runs' last minutes as it stops, within STOP_ROLLUP_S
    print("demo: stopped", flush=True)


def _wait(proc: subprocess.Popen, timeout: float) -> None:
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
