"""PTP end to end: a real relay on the monitoring host (the grandmaster's namespace), a real node
(probes.ship.simnode) in the PTP client's namespace reading its ptp4l with ``--ptp-socket``; the
relay's API and the UI's nodes panel show the node's PTP state; killing the grandmaster turns
it "lost" within the stated bound while ``auto`` applies the estimate and says why.

Layout: the relay listens in the grandmaster's namespace (as on the monitoring host, which is
the grandmaster); the node reaches it over the PTP link; this test and its browser reach it
over a further veth pair from the host into that namespace."""

from __future__ import annotations

import json
import sys
import time
import urllib.request

import pytest

from tests.ptpnet import GM_ADDR, PtpNet, field, pmc, require_linuxptp
from tests.ui.helpers import env

RELAY_PORT = 3000
"""Free in any fresh namespace."""
POLL_S, REPORT_S, PMC_S = 2.0, 2.0, 2.0
"""The node's pmc poll, its clock-report interval (RelayExporter's defaults) and pmc's timeout."""


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    require_linuxptp()
    tmp = tmp_path_factory.mktemp("ptpui")
    with PtpNet(tmp, host_link=True) as net:
        net.spawn(net.gm_ns, [sys.executable, "-m", "dcuscope.cli", "relay", "--host", "0.0.0.0", "--port",
                              str(RELAY_PORT), "--db", str(tmp / "relay.db")], "relay", env=env())
        url = f"http://{net.relay_addr}:{RELAY_PORT}"
        _wait(lambda: _get(url, "/api/nodes") is not None, 30, "relay did not answer", net, "relay")
        net.spawn(net.client_ns, [sys.executable, "-m", "dcuscope.probes.ship.simnode", "--relay", f"http://{GM_ADDR}:{RELAY_PORT}",
                                  "--node", "DCU-PTP", "--ptp-socket", str(net.client_uds), "--paced",
                                  "--frames", "3000", "--fps", "25", "--sources", "1"], "node", env=env())
        yield net, url


def _get(url: str, path: str):
    try:
        with urllib.request.urlopen(url + path, timeout=5) as r:
            return json.load(r)
    except OSError:
        return None


def _wait(cond, timeout_s: float, what: str, net: PtpNet, log: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = cond()
        if got:
            return got
        time.sleep(0.2)
    raise AssertionError(f"{what} within {timeout_s} s; {log} log:\n{net.log(log)}")


def _node(url: str) -> dict | None:
    nodes = _get(url, "/api/nodes") or []
    return next((n for n in nodes if n["node"] == "DCU-PTP"), None)


def test_relay_and_ui_show_ptp_then_lost_when_the_grandmaster_dies(setup, browser):
    net, url = setup
    node = _wait(lambda: (n := _node(url)) and n["ptp"]["state"] == "locked" and n["clock"]["samples"]
                 and abs(n["ptp"]["master_offset_ns"]) < 10_000 and n,
                 40, "no PTP report with a master offset under 10 µs reached the relay", net, "node")
    ptp, clock = node["ptp"], node["clock"]
    gm = net.gm_identity()
    assert (ptp["port_state"], ptp["gm_identity"], ptp["gm_present"], ptp["timestamping"]) == ("SLAVE", gm, True, "software")
    # ptp4l locked, but free-running: CLOCK_REALTIME follows nothing, so auto applies the estimate
    assert ptp["system_clock"]["follows_ptp"] is False
    assert clock["mode"] == "auto" and clock["applied"] == "estimate"
    assert clock["why"].startswith("PTP not trusted: ptp4l locked but CLOCK_REALTIME not disciplined by PTP "
                                   "(ptp4l free_running, no phc2sys") and clock["why"].endswith("; estimate applied")

    page = browser.new_page()
    try:
        page.goto(url + "/", wait_until="domcontentloaded")
        row = page.locator('#nodes-panel tr[data-node="DCU-PTP"]')
        row.wait_for(timeout=20_000)
        page.wait_for_function("() => document.querySelector('#nodes-panel tr[data-node=\"DCU-PTP\"] .ptp-state')"
                               "?.textContent === 'locked'", timeout=20_000)
        # At a glance: ptp4l locked, but the clock is the relay's estimate (CLOCK_REALTIME follows nothing).
        assert row.locator(".clock-state").inner_text() == "estimate"
        assert "CLOCK_REALTIME not disciplined by PTP" in row.locator(".clock-cell").get_attribute("title")
        drift = row.locator(".drift").inner_text()
        assert drift == "—" or drift.endswith("ppm"), drift
        # The details, a click away: port, grandmaster, master offset, what CLOCK_REALTIME follows, the why in full.
        row.click()
        detail = page.locator('#nodes-panel tr[data-detail="DCU-PTP"]')
        detail.wait_for(timeout=5_000)
        assert detail.locator(".ptp-port").inner_text() == "SLAVE"
        assert gm in detail.locator(".ptp-gm").inner_text()
        assert detail.locator(".ptp-offset").inner_text().endswith("ns")
        assert "ptp4l free_running, no phc2sys" in detail.locator(".sysclock").inner_text()
        assert "PTP not trusted: ptp4l locked but CLOCK_REALTIME not disciplined by PTP" in detail.locator(".clock-why").inner_text()

        # The bound: the client notices after announceReceiptTimeout + 1 (ptp4l's random span)
        # announce intervals, the node polls every POLL_S (pmc answering within PMC_S), reports every REPORT_S.
        port = pmc(net.client_uds, "GET PORT_DATA_SET")
        announce_s = (int(field(port, "announceReceiptTimeout")) + 1) * 2.0 ** int(field(port, "logAnnounceInterval"))
        bound_s = announce_s + POLL_S + PMC_S + REPORT_S
        killed = net.kill_grandmaster()
        lost = _wait(lambda: (n := _node(url)) and n["ptp"]["state"] == "lost" and n, bound_s + 10,
                     "the node never turned lost", net, "node")
        took = time.monotonic() - killed
        assert took <= bound_s, f"lost after {took:.1f} s, beyond the stated {bound_s:.1f} s"
        assert lost["ptp"]["reason"].startswith(f"lost {gm}: ")
        assert lost["clock"]["applied"] == "estimate" and lost["clock"]["why"].startswith("PTP not trusted: PTP lost (lost ")
        page.wait_for_function("() => document.querySelector('#nodes-panel tr[data-node=\"DCU-PTP\"] .ptp-state')"
                               "?.textContent === 'lost'", timeout=10_000)
        # The detail row stayed open across the refreshes, and now says why PTP is not trusted.
        page.wait_for_function("() => document.querySelector('#nodes-panel tr[data-detail=\"DCU-PTP\"] .clock-why')"
                               "?.textContent.startsWith('PTP not trusted: PTP lost (lost ')", timeout=10_000)
        print(f"grandmaster killed: node lost after {took:.1f} s (bound {bound_s:.1f} s)")
    finally:
        page.close()
