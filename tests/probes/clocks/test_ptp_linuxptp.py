"""The node's PTP reader against real linuxptp: a ptp4l grandmaster and a free-running ptp4l
client in two network namespaces (tests/ptpnet.py), and the shipped configs loaded by ptp4l."""

from __future__ import annotations

import asyncio
import subprocess
import time

import pytest

from dcuscope.probes.clocks.ptp import read_ptp_state
from dcuscope.protocol.ptptrust import ptp_trusted
from tests.ptpnet import CONFIGS, PtpNet, require_linuxptp


@pytest.fixture(scope="module")
def net(tmp_path_factory):
    require_linuxptp()
    with PtpNet(tmp_path_factory.mktemp("ptpnet")) as ptp_net:
        yield ptp_net


def test_node_reads_grandmaster_port_and_offset(net):
    offsets = []
    for _ in range(3):  # a Sync each second: three measurements, judged by their median
        state = asyncio.run(read_ptp_state(str(net.client_uds)))
        assert state["gm_identity"] == net.gm_identity() and state["gm_present"] is True
        assert (state["state"], state["port_state"], state["interface"], state["timestamping"]) == (
            "locked", "SLAVE", net.client_iface, "software")
        offsets.append(abs(state["master_offset_ns"]))
        time.sleep(1)
    assert sorted(offsets)[1] < 10_000, offsets


def test_locked_but_system_clock_not_disciplined_is_not_trusted(net):
    state = asyncio.run(read_ptp_state(str(net.client_uds)))
    assert state["state"] == "locked"
    clock = state["system_clock"]
    assert clock["follows_ptp"] is False and clock["detail"].startswith("ptp4l free_running, no phc2sys")
    trusted, reason = ptp_trusted(state)
    assert not trusted
    assert reason.startswith("ptp4l locked but CLOCK_REALTIME not disciplined by PTP (ptp4l free_running, no phc2sys")


def test_grandmaster_reports_itself_master(net):
    state = asyncio.run(read_ptp_state(str(net.gm_uds)))
    assert (state["state"], state["port_state"], state["gm_present"]) == ("unlocked", "MASTER", False)


@pytest.mark.parametrize("config", ["grandmaster-hw.cfg", "dcu-hw.cfg", "grandmaster-sw.cfg", "dcu-sw.cfg"])
def test_shipped_configs_load_in_ptp4l(net, config, tmp_path):
    """Each config runs ptp4l up to a listening port (software timestamping forced with -S, which
    a veth has; free-running: no clock is touched; PTP domain 1: the test's grandmaster and client,
    in domain 0, never hear it); hardware ones also get past the parser (ptp4l rejects unknown
    options) to the timestamping check a veth fails."""
    uds = tmp_path / "cfg.sock"
    argv = ["ptp4l", "-f", str(CONFIGS / config), "-i", net.gm_iface, "-m", "--free_running", "1",
            "--domainNumber", "1", "--uds_address", str(uds)]
    proc = net.spawn(net.gm_ns, argv + ["-S"], f"load-{config}")
    deadline = time.monotonic() + 15
    while "to LISTENING" not in net.log(f"load-{config}") and time.monotonic() < deadline:
        assert proc.poll() is None, f"ptp4l refused {config}: {net.log(f'load-{config}')}"
        time.sleep(0.2)
    assert "port 1: INITIALIZING to LISTENING" in net.log(f"load-{config}")
    proc.terminate()
    proc.wait(10)
    if config.endswith("-hw.cfg"):
        out = subprocess.run(["ip", "netns", "exec", net.gm_ns, *argv], capture_output=True, text=True, timeout=20)
        assert out.returncode != 0 and "does not support requested timestamping mode" in out.stdout + out.stderr
        assert "failed to parse configuration file" not in out.stdout + out.stderr
