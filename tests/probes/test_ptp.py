"""The node's PTP state: linuxptp's TIME_STATUS_NP as pmc prints it, and pmc on this machine."""

from __future__ import annotations

import asyncio
import shutil

from probes.ptp import parse_time_status, read_ptp_state

PMC_LOCKED = """sending: GET TIME_STATUS_NP
\t90e2ba.fffe.0d8a6c-0 seq 0 RESPONSE MANAGEMENT TIME_STATUS_NP
\t\tmaster_offset              -11
\t\tingress_time               1481209542396429442
\t\tcumulativeScaledRateOffset +0.000000000
\t\tscaledLastGmPhaseChange    0
\t\tgmTimeBaseIndicator        0
\t\tlastGmPhaseChange          0x0000'0000000000000000.0000
\t\tgmPresent                  true
\t\tgmIdentity                 001e67.fffe.e1e2c5
"""


def test_parse_time_status():
    assert parse_time_status(PMC_LOCKED) == {"state": "locked", "master_offset_ns": -11, "gm_present": True,
                                             "gm_identity": "001e67.fffe.e1e2c5"}
    far = PMC_LOCKED.replace("-11", "2500000")
    assert parse_time_status(far)["state"] == "unlocked"
    no_gm = PMC_LOCKED.replace("gmPresent                  true", "gmPresent                  false")
    assert parse_time_status(no_gm)["state"] == "unlocked"
    assert parse_time_status("sending: GET TIME_STATUS_NP\n")["state"] == "unavailable"


def test_read_ptp_state_on_this_machine():
    state = asyncio.run(read_ptp_state(timeout_s=3))
    if shutil.which("pmc") is None:
        assert state == {"state": "unavailable", "reason": "pmc not installed"}
    else:
        assert state["state"] in ("unavailable", "locked", "unlocked")
