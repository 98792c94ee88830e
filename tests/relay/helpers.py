"""Test helpers: a relay process, simulated node processes, JSON over HTTP, stats comparison.

Everything runs on 127.0.0.1 with free ports and bounded waits. A node here is a separate
process (``python -m dcuscope.probes.ship.simnode``) writing the events it shipped to an .npz; a real
``dcuscope run --probes --relay ... --trace FILE`` process can take its place, the test then
reading its trace file instead.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import select
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import aiohttp
import numpy as np

from dcuscope.probes.ship.relaylink import Link
from dcuscope.probes.ship.simnode import header_for
from dcuscope.protocol.events import TraceHeader
from dcuscope.relay.store.runs import list_sessions, load_runs

ROOT = Path(__file__).resolve().parents[2]


def env() -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + os.pathsep + e.get("PYTHONPATH", "")
    return e


class RelayProcess:
    """``python -m dcuscope.relay`` in a subprocess; ``url`` once it listens (at the address it says it listens
    on: 127.0.0.1 unless ``args`` give ``--host``)."""

    def __init__(self, db: Path, port: int = 0, token: str | None = None, clock: str = "auto",
                 log: Path | None = None, args: list[str] | None = None, prefix: list[str] | None = None) -> None:
        """``prefix``: a command that execs the relay's command line it is given (``unshare ...``)."""
        cmd = [*(prefix or []), sys.executable, "-m", "dcuscope.relay", "--port", str(port), "--db", str(db), "--clock", clock,
               *(args or [])]
        if token:
            cmd += ["--token", token]
        self.log = log or db.with_suffix(".relay.log")
        self._log = open(self.log, "ab")
        self.proc = subprocess.Popen(cmd, cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=self._log)
        line = _readline(self.proc, 30)
        m = re.search(r"(https?)://(\S+):(\d+)", line)
        if not m:
            self.stop()
            raise RuntimeError(f"relay did not start: {line!r}; log: {self.log.read_text()[-2000:]}")
        scheme, self.host, self.port = m.group(1), m.group(2).strip("[]"), int(m.group(3))
        self.url = f"{scheme}://[{self.host}]:{self.port}" if ":" in self.host else f"{scheme}://{self.host}:{self.port}"

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)
        self._log.close()

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()
        return self.proc.returncode

    def alive(self) -> bool:
        return self.proc.poll() is None

    def rss_mb(self, field: str = "VmRSS") -> float:
        """The relay's resident memory now (``VmRSS``) or its high-water mark (``VmHWM``), MiB."""
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
        raise AssertionError(f"no {field} for the relay process")

    def peak_rss_mb(self) -> float:
        return self.rss_mb("VmHWM")


def _readline(proc: subprocess.Popen, timeout: float) -> str:
    """A line of ``proc``'s stdout, or what came of it within ``timeout`` s ('' if nothing). Read a
    byte at a time from the pipe itself: through the buffered ``proc.stdout``, two lines that came
    in one read (two workers starting at once) would leave the second in its buffer, where a
    select on the pipe never sees it."""
    fd = proc.stdout.fileno()
    deadline = time.monotonic() + timeout
    line = bytearray()
    while not line.endswith(b"\n"):
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            break
        byte = os.read(fd, 1)
        if not byte:  # the process closed its stdout
            break
        line += byte
    return line.decode(errors="replace")


def start_node(url: str, node: str, out: Path, *, frames: int = 100, sources: int = 2, fps: float = 25.0,
               paced: bool = False, offset_ns: int = 0, t0_ns: int = 0, drop_rate: float = 0.0, seed: int = 0,
               token: str | None = None, extra: list[str] | None = None, linger: bool = False,
               until_stdin: bool = False, prefix: list[str] | None = None) -> subprocess.Popen:
    """A ``probes.ship.simnode`` process; with ``linger`` its run stays open after the last event until
    its stdin closes (``finish_node`` closes it); with ``until_stdin`` (and ``paced``) it stops writing
    events then, ``frames`` being a most. ``prefix``: a command that execs the node's command line it is
    given (``ip netns exec NS``)."""
    cmd = [*(prefix or []), sys.executable, "-m", "dcuscope.probes.ship.simnode", "--relay", url, "--node", node, "--out", str(out),
           "--frames", str(frames), "--sources", str(sources), "--fps", str(fps), "--seed", str(seed),
           "--clock-offset-ns", str(offset_ns), "--drop-rate", str(drop_rate)]
    if paced:
        cmd.append("--paced")
    if t0_ns:
        cmd += ["--t0-ns", str(t0_ns)]
    if token:
        cmd += ["--token", token]
    if linger:
        cmd.append("--linger")
    if until_stdin:
        cmd.append("--until-stdin-closes")
    cmd += extra or []
    return subprocess.Popen(cmd, cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            stdin=subprocess.PIPE if linger or until_stdin else subprocess.DEVNULL)


def finish_node(proc: subprocess.Popen, timeout: float = 60, status: int = 0) -> dict:
    """The node's counters, once it exited with ``status`` (UNACKNOWLEDGED_STATUS: a relay did not
    store all its events)."""
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == status, err.decode()[-3000:]
    return json.loads(out.decode().strip().splitlines()[-1])


def load_node(out: Path) -> tuple[TraceHeader, np.ndarray]:
    z = np.load(out)
    return TraceHeader.from_dict(json.loads(str(z["header"]))), z["events"]


def get_json(url: str, token: str | None = None, timeout: float = 10, context=None):
    """``context``: the SSLContext an https:// ``url`` is verified with."""
    req = urllib.request.Request(url)
    if token:
        req.add_header("Authorization", f"Bearer {token}")
    with urllib.request.urlopen(req, timeout=timeout, context=context) as r:
        return json.loads(r.read())


def http_status(url: str, headers: dict | None = None) -> int:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=10) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def read_http_answer(sock) -> tuple[int, bytes] | None:
    """Status and body of the HTTP answer read from ``sock`` (a 101 has no body); None when the
    connection closes before a whole head, or the head is no HTTP status line."""
    data = b""
    while b"\r\n\r\n" not in data and len(data) < 1 << 16:
        chunk = sock.recv(65536)
        if not chunk:
            return None
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    status = re.match(rb"HTTP/1\.[01] (\d{3})", head)
    if not status:
        return None
    length = re.search(rb"(?i)\r\ncontent-length: *(\d+)", head)
    while length and len(body) < int(length.group(1)):
        chunk = sock.recv(65536)
        if not chunk:
            break
        body += chunk
    return int(status.group(1)), body


def kill_all(procs) -> None:
    """Kill the processes still running (a test's teardown), and reap them."""
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def wait_for(predicate, timeout: float, interval: float = 0.1, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def assert_stats_equal(expected, got, path: str = "stats") -> None:
    """Every key of ``expected`` (node_stats) is in ``got`` with the same value (floats to 1e-9)."""
    if isinstance(expected, dict):
        assert isinstance(got, dict), path
        missing = set(expected) - set(got)
        assert not missing, f"{path}: missing {sorted(missing)}"
        for k in expected:
            assert_stats_equal(expected[k], got[k], f"{path}/{k}")
    elif isinstance(expected, float):
        assert isinstance(got, (int, float)) and abs(expected - got) <= 1e-9 * max(1.0, abs(expected)), \
            f"{path}: {got} != {expected}"
    else:
        assert expected == got, f"{path}: {got!r} != {expected!r}"


def sort_events(events: np.ndarray) -> np.ndarray:
    return np.sort(events, order=["source", "frame", "stage", "point", "ts"])


class HandNode:
    """A node driven by hand on one ingest WebSocket (:class:`dcuscope.probes.ship.relaylink.Link`), for in-process
    tests that send exactly the messages they mean to."""

    def __init__(self, session, link, acks, secret: str | None, reply: dict | None = None) -> None:
        self.session, self.link, self.acks = session, link, acks
        self.reply = reply or {}
        """The relay's hello reply (its UDP clock offer among it)."""
        self.secret = secret
        """The run's resume secret: issued at its first hello, or the one presented."""

    @classmethod
    async def open(cls, url: str, node: str, run: str, token: str | None = None, stages: int = 1,
                   secret: str | None = None, header: TraceHeader | None = None, ssl=None,
                   extra: dict | None = None) -> "HandNode":
        """Say hello for ``run``, as ``node`` with ``header`` (by default that of a simulated node of
        ``stages`` sources); resuming a run takes the ``secret`` its first hello was given. ``ssl``:
        the SSLContext of an https:// ``url``; ``extra``: more fields of the hello."""
        session = aiohttp.ClientSession(connector=aiohttp.TCPConnector(ssl=ssl) if ssl is not None else None)
        acks: asyncio.Queue = asyncio.Queue()
        try:
            link = await Link.open(session, url, token, acks.put_nowait)
            hello = {"proto": 2, "run": run, "header": (header or header_for(node, stages)).to_dict(), "lost": 0}
            if secret is not None:
                hello["secret"] = secret
            hello.update(extra or {})
            reply = await link.call("hello", hello, 5)
        except BaseException:
            await session.close()
            raise
        assert reply["ok"], reply
        return cls(session, link, acks, reply.get("secret", secret), reply)

    async def batch(self, data: bytes) -> dict:
        """Send one batch and wait for its acknowledgement."""
        await self.link.send_batch(data)
        return await asyncio.wait_for(self.acks.get(), 10)

    @property
    def connected(self) -> bool:
        return not self.link.ws.closed

    async def close(self) -> None:
        await self.link.close()
        await self.session.close()


def connected(relay: RelayProcess) -> set[str]:
    """The nodes streaming to ``relay`` (its /api/nodes lists the whole fleet, each with the relay holding it)."""
    try:
        me = get_json(f"{relay.url}/api/health", timeout=2)["relay"]
        return {n["node"] for n in get_json(f"{relay.url}/api/nodes", timeout=2)
                if n["connected"] and not n["ended"] and n["relay"] == me}
    except OSError:
        return set()


def stored_equals_sent(store: str, node: str, sent: np.ndarray) -> None:
    """``node`` has one run in ``store``, holding every event it sent, each once."""
    runs = [r for s in list_sessions(store) for r in s["runs"] if r["node"] == node]
    assert len(runs) == 1, runs  # the node resumed its run: no second one
    (stored,) = load_runs(store, runs[0]["run"], corrected=False)
    assert runs[0]["events"] == len(stored.events) == len(sent), (node, runs[0]["events"], len(stored.events), len(sent))
    assert np.array_equal(sort_events(stored.events), sort_events(sent))  # 0 lost, 0 stored twice
