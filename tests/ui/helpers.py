"""Helpers of the UI tests: a relay on a thread of its own, feeders (simulated or real nodes), Chromium.

The relay is the real one (``relay.server.start_relay``, aiohttp + python-socketio on 127.0.0.1,
behind its connection guard) run on its own event loop in a background thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import signal
import subprocess
import sys
import threading
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

from dcuscope.relay.config import RelayConfig
from dcuscope.relay.guard.auth import Credentials
from dcuscope.relay.guard.limits import Limits
from dcuscope.relay.server import start_relay
from tests.relay.helpers import get_json, wait_for

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = "/usr/bin/chromium"
KEEP_ENDED = Limits(ended_keep_s=3600.0)
"""A relay's limits for a module whose tests read ended runs' live rows for minutes on a loaded machine,
past the 60 s an ended run stays in them by default (``--limit ended_keep_s``)."""
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
REAL_PIPELINES = (ROOT / "probes" / "instrument.py").is_file()
"""Real ``dcuscope run --probes --relay`` nodes exist once probes/instrument.py does."""


def env() -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + os.pathsep + e.get("PYTHONPATH", "")
    return e


class RelayThread:
    """The relay (HTTP API, /ui, /ingest, the page) on a background event loop; ``url`` once up.

    ``port=0`` picks a free port; a relay started again on the port of a stopped one (and its
    database) is that relay restarted. ``token``, ``viewer_tokens`` and ``node_tokens`` are its
    credentials; the other ``options`` are fields of its ``RelayConfig`` (e.g. ``limits``)."""

    def __init__(self, db: Path, token: str | None = None, push_hz: float = 10.0, port: int = 0,
                 viewer_tokens: dict | None = None, node_tokens: dict | None = None, **options) -> None:
        self._db, self._push_hz, self._options = db, push_hz, options
        self._credentials = Credentials(token, viewer_tokens or {}, node_tokens or {})
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self.relay = None
        self.port = port
        self._thread = threading.Thread(target=self._main, name="ui-test-relay", daemon=True)
        self._thread.start()
        if not self._ready.wait(30) or self._error is not None:
            raise RuntimeError(f"relay did not start: {self._error!r}")
        self.url = f"{'https' if options.get('tls') else 'http'}://127.0.0.1:{self.port}"

    def _main(self) -> None:
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        try:
            # The relay as `dcuscope relay` starts it: its guarded site included.
            relay = await start_relay(RelayConfig(self._db, port=self.port, credentials=self._credentials,
                                                  push_hz=self._push_hz, **self._options))
            self.port = relay.port
            self.relay = relay
            self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        except BaseException as exc:  # noqa: BLE001 - reported to the constructor
            self._error = exc
            self._ready.set()
            raise
        self._ready.set()
        try:
            await self._stop.wait()
        finally:
            await relay.stop()

    def call(self, fn):
        """``fn()`` run on the relay's event loop, where its state lives; returns its result."""
        async def run():
            return fn()

        return asyncio.run_coroutine_threadsafe(run(), self._loop).result(10)

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(15)




# --- feeders: what sends probe events to the relay ------------------------------------------------

@dataclass
class Feeder:
    """Node processes feeding a relay; ``kind`` is "sim" (probes.ship.simnode) or "pipeline" (dcuscope run)."""

    kind: str
    nodes: list[str]
    procs: list[subprocess.Popen] = field(default_factory=list)
    outs: list[Path] = field(default_factory=list)

    def wait(self, timeout: float = 120) -> None:
        for p in self.procs:
            out, err = p.communicate(timeout=timeout)
            assert p.returncode == 0, f"{self.kind} node failed: {err.decode(errors='replace')[-3000:]}"

    def end(self, timeout: float = 120) -> None:
        """The nodes' runs end now, cleanly: real pipelines are told to stop (SIGTERM: each ends its
        run as at its ``--duration``); simulated nodes, which cannot stop early, run to their end."""
        if self.kind == "pipeline":
            for p in self.procs:
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
        self.wait(timeout)

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(5)


def sim_nodes(url: str, tmp: Path, nodes: list[str], *, frames: int, sources: int, fps: float, paced: bool,
              token: str | None = None, offsets_ns: list[int] | None = None, seed: int = 0,
              ptp_socket: Path | None = None, t0_ns: int | None = None, extra: list[str] = ()) -> Feeder:
    """``python -m dcuscope.probes.ship.simnode`` per node, each writing the events it shipped to ``tmp/NODE.npz``;
    ``ptp_socket``: the ptp4l socket the nodes read (a path where none is: no PTP, whatever the host runs);
    ``t0_ns``: the true time of every node's frame 0 (default: each node's start + 0.2 s); ``extra``: more
    options of every node (``--relay-ca FILE``)."""
    feeder = Feeder("sim", nodes)
    for k, node in enumerate(nodes):
        out = tmp / f"{node}.npz"
        cmd = [sys.executable, "-m", "dcuscope.probes.ship.simnode", "--relay", url, "--node", node, "--out", str(out),
               "--frames", str(frames), "--sources", str(sources), "--fps", str(fps), "--seed", str(seed + k),
               "--clock-offset-ns", str((offsets_ns or [0] * len(nodes))[k])]
        if paced:
            cmd.append("--paced")
        if token:
            cmd += ["--token", token]
        if ptp_socket is not None:
            cmd += ["--ptp-socket", str(ptp_socket)]
        if t0_ns is not None:
            cmd += ["--t0-ns", str(t0_ns)]
        cmd += extra
        feeder.procs.append(subprocess.Popen(cmd, cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE))
        feeder.outs.append(out)
    return feeder


@contextlib.contextmanager
def streaming_fleet(tmp: Path, nodes: list[str], *, frames: int, sources: int, fps: float, within_s: float):
    """A relay and ``nodes`` simulated DCUs streaming to it (paced), once the overview has a row for
    each (within ``within_s``): yields (relay, feeder); stops both after. Every DCU and page connects
    from 127.0.0.1, so the relay takes 64 connections per peer."""
    relay = RelayThread(tmp / "relay.db", limits=dataclasses.replace(Limits(), connections_per_peer=64))
    feeder = sim_nodes(relay.url, tmp, nodes, frames=frames, sources=sources, fps=fps, paced=True)
    try:
        wait_for(lambda: len(get_json(f"{relay.url}/api/overview")["rows"]) == len(nodes), within_s, 0.3,
                 f"{len(nodes)} DCUs' rows")
        yield relay, feeder
    finally:
        feeder.stop()
        relay.stop()


DEMO_CONFIGS = ("configs/demo-dcu1.yaml", "configs/demo-dcu2.yaml")


def pipeline_nodes(url: str, tmp: Path, nodes: list[str], *, configs: tuple[str, ...] = DEMO_CONFIGS,
                   duration: float = 20.0, token: str | None = None) -> Feeder:
    """``dcuscope run CONFIG --probes --relay URL --node NODE --duration S`` per node (real GStreamer):
    by default the demo's two DCUs (CenterNet over two cameras, SSD over four with a queue)."""
    feeder = Feeder("pipeline", nodes)
    for node, config in zip(nodes, configs):
        cmd = [sys.executable, "-m", "dcuscope.cli", "run", config, "--probes", "--relay", url, "--node", node,
               "--duration", str(duration), "--quiet", "--trace", str(tmp / f"{node}.jsonl")]
        if token:
            cmd += ["--token", token]
        feeder.procs.append(subprocess.Popen(cmd, cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE))
        feeder.outs.append(tmp / f"{node}.jsonl")
    return feeder


def source_fps(url: str, node: str) -> dict[str, float]:
    """``dcuscope_source_fps`` of ``node`` per source, as the relay's ``/metrics`` gives it now."""
    from prometheus_client.parser import text_string_to_metric_families

    with urllib.request.urlopen(f"{url}/metrics", timeout=10) as r:
        text = r.read().decode()
    return {s.labels["source"]: s.value for family in text_string_to_metric_families(text)
            if family.name == "dcuscope_source_fps" for s in family.samples if s.labels["node"] == node}


NETWORK_CHANGED = "net::ERR_NETWORK_CHANGED"
GOTO_TRIES = 3


def _goto_again_when_the_network_changed(goto):
    """``Page.goto``, again (GOTO_TRIES in all) while a request of the page failed with
    net::ERR_NETWORK_CHANGED. Chromium aborts its requests when the host's interfaces change, which
    the tests that make veth pairs and network namespaces do beside the UI's (a CI run lost a sign-in
    page's module script so): not the relay's fault, and a page whose app script was lost cannot
    recover by itself, as a person would by reloading."""
    def go(page, url, **kwargs):
        failed: list[str] = []

        def note(request) -> None:
            failed.append(request.failure or "")

        page.on("requestfailed", note)
        try:
            for _ in range(GOTO_TRIES):
                failed.clear()
                response = goto(page, url, **kwargs)
                if not any(NETWORK_CHANGED in f for f in failed):
                    break
            return response
        finally:
            page.remove_listener("requestfailed", note)
    go.retries_network_changes = True
    return go


def launch_chromium(playwright, extra_args: list[str] | None = None):
    if not Path(CHROMIUM).exists():
        raise RuntimeError(f"{CHROMIUM} not found: install Debian's chromium package")
    from playwright.sync_api import Page

    if not getattr(Page.goto, "retries_network_changes", False):
        Page.goto = _goto_again_when_the_network_changed(Page.goto)
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS + (extra_args or []))


def units_page(browser, db: Path):
    """A page of a relay of its own (database ``db``) for tests of the page's pure JavaScript: yields the
    page, then fails the test if the page raised."""
    relay = RelayThread(db)
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(relay.url + "/")
        page.wait_for_function("window.dcuscope !== undefined", timeout=15000)
        yield page
        assert not errors, errors
    finally:
        page.close()
        relay.stop()


def screenshot_with_address(page, path: Path, height: int = 34) -> None:
    """``page``'s screenshot with a strip above it giving its address (``page.url``), as a browser's
    address bar would: headless Chromium draws none."""
    import cv2
    import numpy as np

    page.screenshot(path=str(path))
    shot = cv2.imread(str(path))
    strip = np.full((height, shot.shape[1], 3), 236, np.uint8)
    cv2.putText(strip, page.url, (12, height - 11), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (40, 40, 40), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), np.vstack([strip, shot]))
