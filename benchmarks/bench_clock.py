"""Clock estimator benchmark: the relay's correction against an injected truth, UDP vs WebSocket.

Each case runs a relay (``python -m dcuscope.relay --clock estimate``) and a simulated node
(``python -m dcuscope.probes.ship.simnode --paced``) whose pretend clock is off by OFFSET and runs DRIFT ppm
fast from a start the benchmark fixes (``--clock-start-ns``), so that the true offset at any
moment is known: true(t) = OFFSET + DRIFT * 1e-6 * (t - start). Every ``--every`` seconds after
a warm-up it reads the relay's clock view of the node (``/api/nodes``: ``correction_ns`` and
``correction_uncertainty_ns``, the correction in force now and its stated bound) and compares:
error = correction - truth; the truth is inside the bound when |error| <= stated.

Transports, side by side (relays and nodes of a group run at once, under the same load):
``udp`` (the relay's UDP clock exchange, kernel timestamps) and ``websocket`` (the relay
started with ``--clock-port 0``: the node falls back to its WebSocket ``sync``). On loopback
the three drifts of one offset form a group (six relays, six nodes); each network path is one.

The relay fits the drift only over 20 s of samples; before, its bound grows with the drift it
cannot rule out, so each row gives the bound at the first read (``stated_first_us``, after the
``--warmup``, 4 s) and at the last (``stated_last_us``, the settled figure), and whether the truth
was inside the bound at every read (``inside``).

Paths: ``loopback`` (127.0.0.1), with offsets 0, 37 ms, -2.5 s and drifts 0, +50, -100 ppm;
``sym-2ms`` and ``asym-1/3ms``: the relay and the node in two network namespaces joined through
a third that forwards every Ethernet frame after a delay (:mod:`benchmarks.delaybridge`, a
userspace bridge on AF_PACKET sockets: ``tc netem`` is not available on this kernel), 2 ms each
way with +-0.5 ms jitter, or 1 ms node->relay and 3 ms relay->node. Needs root for those;
without it they are skipped.

``--minutes M``: one long run instead (loopback, UDP, 37 ms, +50 ppm), sampled every
``--every`` seconds (default 5), summarised per minute. ``--quick``: a smoke test, the network
paths' case (37 ms, +50 ppm) on loopback for 3 s, read every 0.5 s after a 1 s warm-up.

A case whose relay never gave an estimate for its node shows its figures as ``n/a (reason)``
(benchmarks/figures.py); a relay that does not start is said in one line (exit status 2).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_clock.py [--seconds 45] [--warmup 4] [--every 1]
        [--paths loopback sym-2ms asym-1/3ms]
    PYTHONPATH=. .venv/bin/python benchmarks/bench_clock.py --minutes 10
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import NA, CannotRun, dumps, fmt, last_line, run  # noqa: E402

OFFSETS_NS = (0, 37_000_000, -2_500_000_000)
DRIFTS_PPM = (0.0, 50.0, -100.0)
NETNS_CASE = (37_000_000, 50.0)
PATHS = {"loopback": None, "sym-2ms": (2.0, 2.0, 0.5), "asym-1/3ms": (1.0, 3.0, 0.0)}
"""name -> (node->relay ms, relay->node ms, jitter ms) of the bridge; None: loopback."""
NS_RELAY, NS_BRIDGE, NS_NODE = "dcsclk-r", "dcsclk-b", "dcsclk-n"
RELAY_IP, NODE_IP = "10.213.7.1", "10.213.7.2"
WARMUP_S = 4.0
"""Seconds from the start of a group to its first read of the relays (``--warmup``)."""
FPS = 10.0
FIGURES = ("err_max_us", "err_last_us", "stated_first_us", "stated_last_us", "inside")
"""A row's figures, from the reads of the relay's estimate."""


def _env() -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + os.pathsep + e.get("PYTHONPATH", "")
    return e


def _netns(name: str | None) -> list[str]:
    return ["ip", "netns", "exec", name] if name else []


@dataclass
class Run:
    """One relay and one node with a pretend clock, and what was read of the relay meanwhile."""
    transport: str
    offset_ns: int
    drift_ppm: float
    path: str
    seconds: float
    errors_ns: list[int] = field(default_factory=list)
    stated_ns: list[int] = field(default_factory=list)
    via: str = ""
    unread: str = "the relay was never read"
    """Why the last read that gave no estimate gave none (the reason of a row without reads)."""

    def start_relay(self, db: Path) -> None:
        """Its relay's process, starting (:meth:`start_node` waits until it listens)."""
        netns = PATHS[self.path] is not None
        host = RELAY_IP if netns else "127.0.0.1"
        cmd = [*_netns(NS_RELAY if netns else None), sys.executable, "-m", "dcuscope.relay", "--host", host,
               "--port", "0", "--db", str(db), "--clock", "estimate"]
        if self.transport == "websocket":
            cmd += ["--clock-port", "0"]
        self._host = host
        self._errors = tempfile.TemporaryFile()  # not a pipe: nobody reads it while the relay runs
        self.relay = subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=self._errors)

    def start_node(self) -> None:
        """Once its relay listens, its node, whose pretend clock starts now."""
        netns = PATHS[self.path] is not None
        host = self._host
        line = self.relay.stdout.readline().decode()
        m = re.search(r"http://[\d.]+:(\d+)", line)
        if not m:
            self.relay.kill()
            self.relay.wait(15)
            self._errors.seek(0)
            raise CannotRun(f"the relay did not start: {last_line(self._errors.read())}")
        self.url = f"http://{host}:{m.group(1)}"
        self.netns = NS_RELAY if netns else None
        self.start_ns = time.clock_gettime_ns(time.CLOCK_REALTIME)
        frames = int(self.seconds * FPS)
        self.node = subprocess.Popen(
            [*_netns(NS_NODE if netns else None), sys.executable, "-m", "dcuscope.probes.ship.simnode", "--relay", self.url,
             "--node", "N", "--frames", str(frames), "--sources", "1", "--fps", str(FPS), "--paced",
             "--clock-offset-ns", str(self.offset_ns), "--clock-drift-ppm", str(self.drift_ppm),
             "--clock-start-ns", str(self.start_ns)],
            cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)

    def truth(self, real_ns: int) -> float:
        """The true offset (node - relay) when CLOCK_REALTIME reads ``real_ns`` (one machine: the
        relay's clock, and the node's before its pretence)."""
        return self.offset_ns + self.drift_ppm * 1e-6 * (real_ns - self.start_ns)

    def sample(self) -> None:
        before = time.time_ns()
        nodes = self._get("/api/nodes")
        after = time.time_ns()
        clock = next((n["clock"] for n in nodes if n["node"] == "N"), None)
        if clock is None:
            self.unread = "the node never reached the relay"
            return
        if clock.get("applied") != "estimate":
            self.unread = f"the relay applied no estimate (applied: {clock.get('applied')})"
            return
        # The relay evaluates its correction at the node's now (its own now + the offset).
        self.errors_ns.append(int(round(clock["correction_ns"] - self.truth((before + after) // 2))))
        self.stated_ns.append(int(clock["correction_uncertainty_ns"]))
        self.via = clock.get("via", self.via)

    def _get(self, path: str):
        if self.netns is None:
            with urllib.request.urlopen(self.url + path, timeout=10) as r:
                return json.loads(r.read())
        out = subprocess.run([*_netns(self.netns), "curl", "-sf", "--max-time", "10", self.url + path],
                             capture_output=True, check=True)
        return json.loads(out.stdout)

    def finish(self) -> None:
        try:
            out, _ = self.node.communicate(timeout=self.seconds + 60)
        except subprocess.TimeoutExpired:
            self.node.kill()
            out, _ = self.node.communicate()
        lines = out.decode().strip().splitlines()
        counters = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}
        self.via = self.via or counters.get("clock_via", "")
        self.relay.terminate()
        self.relay.wait(15)
        self._errors.close()

    def row(self, first: int = 0, last: int | None = None) -> dict:
        err = np.array(self.errors_ns[first:last], dtype=np.int64)
        stated = np.array(self.stated_ns[first:last], dtype=np.int64)
        row = {"path": self.path, "transport": self.transport, "via": self.via or NA("the node did not say"),
               "offset_ms": self.offset_ns / 1e6, "drift_ppm": self.drift_ppm, "reads": len(err)}
        if len(err) == 0:
            none = NA(f"no estimate read: {self.unread}")
            return dict(row, **{key: none for key in FIGURES})
        return dict(row, err_max_us=float(np.abs(err).max()) / 1e3, err_last_us=float(err[-1]) / 1e3,
                    stated_first_us=float(stated[0]) / 1e3, stated_last_us=float(stated[-1]) / 1e3,
                    inside=bool((np.abs(err) <= stated).all()))


def run_together(runs: list[Run], every_s: float, tmp: Path, warmup_s: float = WARMUP_S) -> None:
    try:
        for i, r in enumerate(runs):  # the relays start together, each node as soon as its relay listens
            r.start_relay(tmp / f"r{i}-{time.monotonic_ns()}.db")
        for r in runs:
            r.start_node()
        deadline = time.monotonic() + runs[0].seconds
        time.sleep(warmup_s)
        while time.monotonic() < deadline:
            for r in runs:
                r.sample()
            time.sleep(every_s)
        for r in runs:
            r.finish()
    finally:
        for proc in [p for r in runs for p in (getattr(r, "node", None), getattr(r, "relay", None)) if p]:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)


def netns_up(path: str) -> subprocess.Popen:
    """Relay and node namespaces joined through a bridge namespace delaying each frame."""
    netns_down()
    sh = ["set -e"]
    for ns in (NS_RELAY, NS_BRIDGE, NS_NODE):
        sh += [f"ip netns add {ns}", f"ip -n {ns} link set lo up"]
    sh += [f"ip link add r0 netns {NS_RELAY} type veth peer name br0 netns {NS_BRIDGE}",
           f"ip link add n0 netns {NS_NODE} type veth peer name br1 netns {NS_BRIDGE}",
           f"ip -n {NS_RELAY} addr add {RELAY_IP}/24 dev r0", f"ip -n {NS_NODE} addr add {NODE_IP}/24 dev n0"]
    for ns, dev in ((NS_RELAY, "r0"), (NS_BRIDGE, "br0"), (NS_BRIDGE, "br1"), (NS_NODE, "n0")):
        sh.append(f"ip -n {ns} link set {dev} up")
    subprocess.run(["sh", "-c", "\n".join(sh)], check=True)
    bridge = [sys.executable, str(ROOT / "benchmarks" / "delaybridge.py")]
    for ns, devs in ((NS_RELAY, ["r0"]), (NS_NODE, ["n0"]), (NS_BRIDGE, ["br0", "br1"])):
        subprocess.run([*_netns(ns), *bridge, "--offloads-off", *devs], check=True)
    to_relay, to_node, jitter = PATHS[path]
    proc = subprocess.Popen([*_netns(NS_BRIDGE), *bridge, "br0", "br1", "--a-to-b-ms", str(to_node),
                             "--b-to-a-ms", str(to_relay), "--jitter-ms", str(jitter)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    if not proc.stdout.readline():  # it announces its directions once it forwards
        raise OSError(f"the delay bridge did not start: {last_line(proc.communicate()[1])}")
    return proc


def netns_down() -> None:
    for ns in (NS_RELAY, NS_BRIDGE, NS_NODE):
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def groups(paths: list[str], quick: bool = False) -> list[tuple[str, list[tuple[int, float]]]]:
    """(path, [(offset, drift)]) run together: on loopback one group per offset (``quick``: the
    network paths' case alone)."""
    out = []
    for path in paths:
        if PATHS[path] is None:
            out += [(path, [NETNS_CASE])] if quick else [(path, [(o, d) for d in DRIFTS_PPM]) for o in OFFSETS_NS]
        else:
            out.append((path, [NETNS_CASE]))
    return out


def print_table(rows: list[dict]) -> None:
    head = ("path", "transport", "via", "offset_ms", "drift_ppm", "reads", *FIGURES)
    print(" | ".join(head))
    print(" | ".join("---" for _ in head))
    for r in rows:
        print(" | ".join(fmt(r.get(k), ".1f" if isinstance(r.get(k), float) else "") for k in head), flush=True)


def bench_grid(args: argparse.Namespace, tmp: Path) -> list[dict]:
    rows = []
    for path, grid in groups(args.paths, args.quick):
        bridge = None
        if PATHS[path] is not None:
            if os.geteuid() != 0:
                print(f"# {path}: skipped (network namespaces need root)", flush=True)
                continue
            try:
                bridge = netns_up(path)
            except (subprocess.CalledProcessError, OSError) as exc:
                netns_down()
                print(f"# {path}: skipped (its network namespaces could not be set up: {exc})", flush=True)
                continue
        try:
            runs = [Run(t, offset, drift, path, args.seconds) for offset, drift in grid for t in ("websocket", "udp")]
            run_together(runs, args.every or 1.0, tmp, args.warmup)
            for r in runs:
                rows.append(r.row())
                print(dumps(rows[-1]), flush=True)
        finally:
            if bridge is not None:
                bridge.terminate()
                bridge.wait(5)
                netns_down()
    return rows


def bench_long(args: argparse.Namespace, tmp: Path) -> list[dict]:
    run = Run("udp", 37_000_000, 50.0, "loopback", args.minutes * 60)
    run_together([run], args.every or 5.0, tmp, args.warmup)
    per_minute = max(1, int(60 / (args.every or 5.0)))
    rows = [dict(run.row(m, m + per_minute), path=f"minute {m // per_minute + 1}")
            for m in range(0, len(run.errors_ns), per_minute)]
    return rows + [dict(run.row(), path="whole run")]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=45.0, help="length of each group of cases (default 45)")
    p.add_argument("--every", type=float, help="seconds between reads of the relay (default 1; 5 with --minutes)")
    p.add_argument("--warmup", type=float, default=WARMUP_S,
                   help=f"seconds from the start to the first read (default {WARMUP_S:g})")
    p.add_argument("--paths", nargs="+", choices=list(PATHS), default=list(PATHS))
    p.add_argument("--minutes", type=float, help="one long run (loopback, UDP, 37 ms, +50 ppm) instead of the grid")
    p.add_argument("--json", type=Path, help="also write the rows here")
    p.add_argument("--quick", action="store_true",
                   help="a smoke test: 37 ms, +50 ppm on loopback, 3 s, read every 0.5 s after a 1 s warm-up")
    args = p.parse_args(argv)
    if args.quick:
        args.seconds, args.warmup, args.every, args.paths, args.minutes = 3.0, 1.0, 0.5, ["loopback"], None
    if args.warmup < 0 or args.seconds <= args.warmup or (args.every is not None and args.every <= 0):
        p.error(f"--seconds must be over the {args.warmup:g} s warm-up, --warmup not negative, --every positive")
    print(f"# bench_clock on {os.uname().nodename}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}",
          flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        rows = bench_long(args, Path(tmp)) if args.minutes else bench_grid(args, Path(tmp))
    print()
    print_table(rows)
    if args.json:
        args.json.write_text(dumps(rows, indent=1))
    return 0 if rows and all(r.get("inside") for r in rows) else 1


if __name__ == "__main__":
    sys.exit(run(main))
