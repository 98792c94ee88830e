"""A real PTP network for tests: linuxptp's ptp4l grandmaster and client in two network
namespaces joined by a veth pair, software timestamping, neither ever adjusting a clock.

- grandmaster: ``configs/ptp/grandmaster-sw.cfg`` (``masterOnly 1``) with ``--free_running 1``:
  ptp4l on CLOCK_REALTIME otherwise writes the kernel's clock status at start (its
  ``sysclk_set_leap(0)``), and tests must not touch the host's clock;
- client: ``configs/ptp/dcu-sw.cfg`` with ``--free_running 1``: it measures its offset to the
  grandmaster and never steers. A free-running ptp4l 3.1.1 stays UNCALIBRATED unless told that
  its synchronisation is certain (``SET SYNCHRONIZATION_UNCERTAIN_NP 0``, the management message
  meant for a clock disciplined by someone else): told so, its port becomes SLAVE;
- each with its own ``uds_address`` in the test's folder, so ``pmc -s`` reaches each one;
- both announce every second (``--logAnnounceInterval 0``) so that the grandmaster takes its
  role and the client notices it gone within seconds, not tens of seconds.

The namespaces and links have unique names; :meth:`PtpNet.close` removes them and ends the
processes whatever happened (namespaces are removed even when a step of the setup failed).
Optionally a third veth pair joins the host to the grandmaster's namespace (the monitoring
host), so that the test and its browser reach a relay running there.
"""

from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs" / "ptp"
GM_ADDR, CLIENT_ADDR = "10.77.0.1", "10.77.0.2"
"""Addresses inside the two namespaces (private to them: no clash with the host or other tests)."""
LOCK_TIMEOUT_S = 60.0
SETTLED_NS = 10_000
TEST_OVERRIDES = ("--free_running", "1", "--logAnnounceInterval", "0")


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


def netns_permitted() -> str | None:
    """Why network namespaces cannot be used here (None: they can)."""
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add)"
    name = f"dcsprobe{os.getpid()}"
    try:
        made = _ip("netns", "add", name, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"ip netns unusable: {exc}"
    if made.returncode != 0:
        return f"ip netns add not permitted: {made.stderr.strip()}"
    _ip("netns", "del", name, check=False)
    return None


def pair_namespaces(a: tuple[str, str, str], b: tuple[str, str, str]) -> None:
    """Two new network namespaces joined by a veth pair: each (namespace, its end, its /24 address),
    their loopbacks up."""
    (a_ns, a_if, _), (b_ns, b_if, _) = a, b
    _ip("netns", "add", a_ns)
    _ip("netns", "add", b_ns)
    _ip("link", "add", a_if, "netns", a_ns, "type", "veth", "peer", "name", b_if, "netns", b_ns)
    for ns, dev, addr in (a, b):
        _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
        _ip("-n", ns, "link", "set", dev, "up")
        _ip("-n", ns, "link", "set", "lo", "up")


def end_processes(procs: list[subprocess.Popen]) -> None:
    """End each process still running (each a session leader: its group goes too), newest first:
    SIGTERM, then SIGKILL after 10 s."""
    for proc in reversed(procs):
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(10)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5)


def require_linuxptp() -> None:
    """Skip where namespaces are not permitted; fail (not skip) where linuxptp is missing, which
    the setup installs."""
    why = netns_permitted()
    if why is not None:
        pytest.skip(why)
    for tool in ("ptp4l", "pmc"):
        assert subprocess.run(["which", tool], capture_output=True).returncode == 0, (
            f"{tool} not found: scripts/setup.sh installs linuxptp")


def pmc(socket: Path, *queries: str) -> str:
    return subprocess.run(["pmc", "-u", "-b", "0", "-s", str(socket), *queries], capture_output=True,
                          text=True, timeout=10).stdout


def field(text: str, name: str) -> str | None:
    m = re.search(rf"^\s+{name}\s+(\S+)", text, re.MULTILINE)
    return m.group(1) if m else None


class PtpNet:
    """Grandmaster namespace ``gm_ns`` and client namespace ``client_ns``; sockets ``gm_uds``,
    ``client_uds``; ``host_addr``/``relay_addr`` of the optional host link."""

    def __init__(self, tmp: Path, host_link: bool = False) -> None:
        tag = f"ptp{os.getpid() % 100000:05d}{random.randrange(16 ** 3):03x}"
        self.gm_ns, self.client_ns, self.tmp = f"{tag}-gm", f"{tag}-cl", tmp
        self._veth, self._host_veth = (f"{tag}g", f"{tag}c"), (f"{tag}h", f"{tag}r")
        self.gm_uds, self.client_uds = tmp / "gm.sock", tmp / "client.sock"
        self.gm_iface, self.client_iface = self._veth
        self.host_link = host_link
        self.relay_addr = self.host_addr = None
        self.gm: subprocess.Popen | None = None
        self.client: subprocess.Popen | None = None
        self._procs: list[subprocess.Popen] = []

    def __enter__(self) -> PtpNet:
        try:
            self._make_links()
            self.gm = self.spawn(self.gm_ns, self._ptp4l("grandmaster-sw.cfg", self.gm_iface, self.gm_uds), "gm")
            self.client = self.spawn(self.client_ns, self._ptp4l("dcu-sw.cfg", self.client_iface, self.client_uds),
                                     "client")
            self.wait_locked()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _make_links(self) -> None:
        pair_namespaces((self.gm_ns, self._veth[0], GM_ADDR), (self.client_ns, self._veth[1], CLIENT_ADDR))
        if self.host_link:
            self._make_host_link()

    def _make_host_link(self) -> None:
        """A /30 the host does not use yet, host side .2, grandmaster side .1."""
        used = _ip("-4", "-o", "addr").stdout
        net = next(f"10.{o2}.{o3}" for o2, o3 in ((random.randrange(100, 250), random.randrange(256)) for _ in range(100))
                   if f" 10.{o2}.{o3}." not in used)
        h, r = self._host_veth
        _ip("link", "add", h, "type", "veth", "peer", "name", r, "netns", self.gm_ns)
        _ip("addr", "add", f"{net}.2/30", "dev", h)
        _ip("link", "set", h, "up")
        _ip("-n", self.gm_ns, "addr", "add", f"{net}.1/30", "dev", r)
        _ip("-n", self.gm_ns, "link", "set", r, "up")
        self.host_addr, self.relay_addr = f"{net}.2", f"{net}.1"

    def _ptp4l(self, config: str, iface: str, uds: Path) -> list[str]:
        return ["ptp4l", "-f", str(CONFIGS / config), "-i", iface, "-m", "-q", *TEST_OVERRIDES,
                "--uds_address", str(uds)]

    def spawn(self, ns: str, argv: list[str], log: str, env: dict | None = None) -> subprocess.Popen:
        """``argv`` in namespace ``ns``, output to ``tmp/LOG.log``; ended by :meth:`close`."""
        with open(self.tmp / f"{log}.log", "wb") as out:
            proc = subprocess.Popen(["ip", "netns", "exec", ns, *argv], stdout=out, stderr=subprocess.STDOUT,
                                    env=env, cwd=ROOT, start_new_session=True)
        self._procs.append(proc)
        return proc

    def log(self, name: str) -> str:
        path = self.tmp / f"{name}.log"
        return path.read_text(errors="replace")[-3000:] if path.exists() else ""

    def wait_locked(self, timeout_s: float = LOCK_TIMEOUT_S) -> str:
        """Until the client is a SLAVE port within SETTLED_NS of the grandmaster; its pmc answer."""
        deadline, told = time.monotonic() + timeout_s, False
        while time.monotonic() < deadline:
            for proc, name in ((self.gm, "gm"), (self.client, "client")):
                assert proc.poll() is None, f"ptp4l {name} exited: {self.log(name)}"
            text = pmc(self.client_uds, "GET TIME_STATUS_NP", "GET PORT_DATA_SET")
            state, offset = field(text, "portState"), field(text, "master_offset")
            if state == "UNCALIBRATED" and not told:
                pmc(self.client_uds, "SET SYNCHRONIZATION_UNCERTAIN_NP 0")
                told = True
            # 0 until the first path delay is measured: not yet an offset
            if state == "SLAVE" and field(text, "gmPresent") == "true" and 0 < abs(int(offset)) < SETTLED_NS:
                return text
            time.sleep(0.5)
        raise AssertionError(f"client not SLAVE within {SETTLED_NS} ns after {timeout_s:.0f} s:\n"
                             f"{pmc(self.client_uds, 'GET TIME_STATUS_NP', 'GET PORT_DATA_SET')}\n"
                             f"client log:\n{self.log('client')}\ngrandmaster log:\n{self.log('gm')}")

    def gm_identity(self) -> str | None:
        # pmc waits ~100 ms for an answer: a grandmaster busy on a loaded machine can miss it once.
        for _ in range(5):
            identity = field(pmc(self.gm_uds, "GET DEFAULT_DATA_SET"), "clockIdentity")
            if identity is not None:
                return identity
            time.sleep(0.2)
        return None

    def kill_grandmaster(self) -> float:
        """SIGKILL the grandmaster's ptp4l; the monotonic time it was gone."""
        os.killpg(self.gm.pid, signal.SIGKILL)
        self.gm.wait(10)
        return time.monotonic()

    def close(self) -> None:
        end_processes(self._procs)
        for ns in (self.gm_ns, self.client_ns):
            _ip("netns", "del", ns, check=False)  # takes its ends of the veth pairs, and so the pairs
        _ip("link", "del", self._host_veth[0], check=False)
