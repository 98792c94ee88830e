"""The node's PTP report: pmc's answers and adjtimex as captured on this machine (linuxptp 3.1.1,
tests/probes/clocks/data/pmc_*.txt), what disciplines CLOCK_REALTIME, and when ``auto`` trusts PTP."""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path

import pytest

from dcuscope.probes.clocks.ptp import PtpWatch, parse_pmc, parse_time_status, read_ptp_state
from dcuscope.protocol.ptptrust import PTP_LOCK_NS, ptp_trusted, ptp_uncertainty_ns
from dcuscope.probes.clocks.sysclock import (STA_UNSYNC, KernelClock, Proc, Witnesses, parse_chrony_tracking, phc2sys_source, ptp4l_setup,
                             read_adjtimex, system_clock)

DATA = Path(__file__).parent / "data"
ROOT = Path(__file__).resolve().parents[3]
UDS = "/tmp/ptpcap/client.sock"
UNSYNCED = KernelClock(status=STA_UNSYNC, maxerror_us=16_000_000, esterror_us=16_000_000, freq_ppm=0.0)
"""adjtimex on this machine (nothing disciplines its clock): status 0x40, both errors 16 s."""
CLIENT_ARGV = ("ptp4l", "-f", str(ROOT / "configs/ptp/dcu-sw.cfg"), "-i", "ptpx-b", "-m", "-q", "--free_running", "1",
               "--logAnnounceInterval", "0", "--uds_address", UDS)
"""/proc/PID/cmdline of the tests' free-running client (tests/ptpnet.py)."""


def pmc_text(name: str) -> str:
    return (DATA / f"pmc_{name}.txt").read_text()


def test_parse_pmc_answers_interleaved_with_sending_lines():
    answers = parse_pmc(pmc_text("grandmaster"))
    assert set(answers) == {"TIME_STATUS_NP", "PORT_DATA_SET", "PORT_PROPERTIES_NP"}
    assert answers["PORT_DATA_SET"][0]["portState"] == "MASTER"
    assert answers["TIME_STATUS_NP"][0]["gmIdentity"] == "a63bb1.fffe.8ad299"


def test_report_of_a_slave_port():
    assert parse_time_status(pmc_text("client_slave")) == {
        "state": "locked", "reason": "slave of 028144.fffe.b2fc82", "master_offset_ns": -858, "gm_present": True,
        "gm_identity": "028144.fffe.b2fc82", "port_state": "SLAVE", "timestamping": "software", "interface": "ptpx-b"}


@pytest.mark.parametrize("name, reason", [
    ("client_listening", "port LISTENING, not SLAVE"),  # slaveOnly client, grandmaster killed: gmPresent stays true
    ("client_master", "no grandmaster (port MASTER)"),   # client that may be master, grandmaster killed
    ("grandmaster", "no grandmaster (port MASTER)"),
])
def test_report_of_ports_that_follow_no_master(name, reason):
    report = parse_time_status(pmc_text(name))
    assert (report["state"], report["reason"]) == ("unlocked", reason)


def test_report_without_answer_and_far_offsets():
    assert parse_time_status("sending: GET TIME_STATUS_NP\n")["state"] == "unavailable"
    far = pmc_text("client_slave").replace("-858", str(-PTP_LOCK_NS - 1))
    assert parse_time_status(far)["reason"] == f"|master offset| {PTP_LOCK_NS + 1} ns above {PTP_LOCK_NS} ns"


def test_watch_turns_a_locked_port_that_leaves_slave_lost_until_it_locks_again():
    watch = PtpWatch(UDS)
    assert watch.update(parse_time_status(pmc_text("client_listening")))["state"] == "unlocked"  # never locked
    assert watch.update(parse_time_status(pmc_text("client_slave")))["state"] == "locked"
    lost = watch.update(parse_time_status(pmc_text("client_listening")))
    assert (lost["state"], lost["reason"]) == ("lost", "lost 028144.fffe.b2fc82: port LISTENING, not SLAVE")
    gone = watch.update(parse_time_status(pmc_text("client_master")))
    assert (gone["state"], gone["reason"]) == ("lost", "lost 028144.fffe.b2fc82: grandmaster gone")
    silent = watch.update({"state": "unavailable", "reason": "no answer from ptp4l at x"})
    assert silent == {"state": "lost", "reason": "lost 028144.fffe.b2fc82: no answer from ptp4l at x"}
    assert watch.update(parse_time_status(pmc_text("client_slave")))["state"] == "locked"


def test_phc2sys_source_direction():
    cases = {("-s", "eth0", "-w"): "eth0", ("-seth0", "-O0"): "eth0", ("-s", "/dev/ptp0", "-w"): "/dev/ptp0",
             ("-a", "-r"): "auto", ("-a", "-rr"): "auto", ("-a",): None,
             ("-s", "CLOCK_REALTIME", "-c", "eth0", "-w"): None,  # the grandmaster's: system clock -> PHC
             ("-c", "/dev/ptp0", "-s", "CLOCK_REALTIME", "-O", "35"): None,
             ("-s", "eth0", "-c", "/dev/ptp1"): None}
    for args, source in cases.items():
        assert phc2sys_source(Proc(1, "phc2sys", ("phc2sys", *args))) == source, args


def test_ptp4l_setup_reads_arguments_over_its_config_file():
    setup = ptp4l_setup(Proc(7, "ptp4l", CLIENT_ARGV))
    assert (setup.uds, setup.software, setup.free_running, setup.interfaces) == (UDS, True, True, ("ptpx-b",))
    hw = ptp4l_setup(Proc(8, "ptp4l", ("ptp4l", "-f", str(ROOT / "configs/ptp/dcu-hw.cfg"), "-i", "eth0")))
    assert (hw.uds, hw.software, hw.free_running) == ("/var/run/ptp4l", False, False)
    assert ptp4l_setup(Proc(9, "ptp4l", ("ptp4l", "-S", "-i", "eth0"))).software


def witnesses(*argvs: tuple[str, ...], kernel: KernelClock = UNSYNCED, chrony: dict | None = None,
              phcs: frozenset = frozenset()) -> Witnesses:
    return Witnesses(kernel, tuple(Proc(k + 10, Path(a[0]).name, a) for k, a in enumerate(argvs)), chrony, phcs)


SYNCED = KernelClock(status=0x2001, maxerror_us=500, esterror_us=3, freq_ppm=-12.5)


def test_system_clock_of_the_free_running_client_follows_nothing():
    clock = system_clock(witnesses(CLIENT_ARGV), "ptpx-b", UDS)
    assert clock == {"synced": False, "maxerror_us": 16_000_000, "esterror_us": 16_000_000, "freq_ppm": 0.0,
                     "by": None, "follows_ptp": False, "detail": "ptp4l free_running, no phc2sys"}


@pytest.mark.parametrize("argvs, chrony, by, follows, detail", [
    ((("/usr/sbin/phc2sys", "-s", "eth0", "-w"),), None, "phc2sys", True, "phc2sys steers it from this port's clock (phc2sys -s eth0 -w)"),
    ((("phc2sys", "-s", "/dev/ptp0", "-w"),), None, "phc2sys", True, "phc2sys steers it from this port's clock (phc2sys -s /dev/ptp0 -w)"),
    ((("phc2sys", "-a", "-r", "-z", UDS),), None, "phc2sys", True, f"phc2sys steers it from this port's clock (phc2sys -a -r -z {UDS})"),
    ((("phc2sys", "-a", "-r"),), None, "phc2sys", False,  # follows another ptp4l (the default socket)
     "phc2sys steers it from the ptp4l at /var/run/ptp4l, not from eth0"),
    ((("phc2sys", "-s", "/dev/ptp1", "-w"),), None, "phc2sys", False, "phc2sys steers it from /dev/ptp1, not from eth0"),
    ((("ptp4l", "-S", "-i", "eth0", "--uds_address", UDS),), None, "ptp4l", True, "ptp4l steers it (software timestamping)"),
    ((("ptp4l", "-i", "eth0", "--uds_address", UDS),), None, None, False, "ptp4l steers only its NIC's hardware clock, no phc2sys"),
    ((("chronyd",),), {"reference": "PHC0", "phc": True, "synced": True}, "chrony", True,
     "chrony follows PTP hardware clock refclock PHC0"),
    ((("chronyd",),), {"reference": "192.0.2.1", "phc": False, "synced": True}, "chrony", False,
     "no phc2sys, chrony follows 192.0.2.1"),
    ((("ntpd", "-g"),), None, "ntpd", False, "no phc2sys, ntpd steers it"),
    ((), None, None, False, "no phc2sys, no clock daemon seen"),
])
def test_system_clock_by_what(argvs, chrony, by, follows, detail):
    clock = system_clock(witnesses(*argvs, kernel=SYNCED, chrony=chrony, phcs=frozenset({"/dev/ptp0"})), "eth0", UDS)
    assert (clock["by"], clock["follows_ptp"], clock["detail"], clock["synced"]) == (by, follows, detail, True)


def test_chrony_tracking_parsed():
    text = ("Reference ID    : 50484330 (PHC0)\nStratum         : 1\nSystem time     : 0.000000072 seconds fast of NTP time\n"
            "Leap status     : Normal\n")
    assert parse_chrony_tracking(text) == {"reference": "PHC0", "phc": True, "synced": True}
    unsync = "Reference ID    : 00000000 ()\nStratum         : 0\nLeap status     : Not synchronised\n"
    assert parse_chrony_tracking(unsync) == {"reference": "", "phc": False, "synced": False}


LOCKED = dict(parse_time_status(pmc_text("client_slave")))


def test_trusted_only_when_the_system_clock_follows_ptp():
    follows = {"synced": True, "by": "phc2sys", "follows_ptp": True, "esterror_us": 16_000_000, "detail": "x"}
    assert ptp_trusted(dict(LOCKED, system_clock=follows)) == (
        True, "PTP locked to 028144.fffe.b2fc82, offset -858 ns, CLOCK_REALTIME by phc2sys")
    free = system_clock(witnesses(CLIENT_ARGV), "ptpx-b", UDS)
    assert ptp_trusted(dict(LOCKED, system_clock=free)) == (
        False, "ptp4l locked but CLOCK_REALTIME not disciplined by PTP (ptp4l free_running, no phc2sys)")
    assert ptp_trusted(dict(LOCKED, system_clock=dict(follows, synced=False)))[1].endswith("(adjtimex STA_UNSYNC)")
    assert ptp_trusted(LOCKED) == (False, "ptp4l locked but the node did not say what disciplines CLOCK_REALTIME")
    assert ptp_trusted(dict(LOCKED, port_state="LISTENING", system_clock=follows))[0] is False
    assert ptp_trusted({"state": "lost", "reason": "lost a: grandmaster gone"}) == (False, "PTP lost (lost a: grandmaster gone)")
    assert ptp_trusted({"state": "unavailable"}) == (False, "PTP unavailable")
    # phc2sys leaves esterror stale (16 s here): only chrony's and ntpd's count
    assert ptp_uncertainty_ns(dict(LOCKED, system_clock=follows)) == 858
    assert ptp_uncertainty_ns(dict(LOCKED, system_clock=dict(follows, by="chrony", esterror_us=4))) == 4858


def test_adjtimex_read_on_this_machine_changes_nothing():
    before = read_adjtimex()
    assert before is not None and isinstance(before.status, int) and before.maxerror_us >= 0
    after = read_adjtimex()
    assert after.status == before.status and after.freq_ppm == before.freq_ppm


def test_read_ptp_state_without_a_ptp4l():
    state = asyncio.run(read_ptp_state("/nonexistent/ptp4l", timeout_s=3))
    if shutil.which("pmc") is None:
        assert state["reason"] == "pmc not installed (Debian package linuxptp)"
    else:
        assert state["reason"] == "no ptp4l socket at /nonexistent/ptp4l (is ptp4l running? its uds_address?)"
    assert state["state"] == "unavailable" and state["system_clock"]["by"] in (None, "phc2sys", "ptp4l", "chrony",
                                                                               "ntpd", "timesyncd")
