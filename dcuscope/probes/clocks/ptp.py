"""The node's PTP state, read from linuxptp's ``pmc``, and whether its CLOCK_REALTIME follows it.

ptp4l disciplines the NIC's hardware clock; what the probes read is CLOCK_REALTIME, which
follows PTP only through phc2sys (or chrony with a PHC refclock, or a ptp4l with software
timestamping that is not ``free_running``). So the report holds both: ptp4l's view (pmc's
TIME_STATUS_NP, PORT_DATA_SET, PORT_PROPERTIES_NP) and the system clock's (:mod:`dcuscope.probes.clocks.sysclock`);
:func:`ptp_trusted` decides from both whether the relay may leave the node's timestamps alone.

The report (sent in the node's hello and every clock message)::

    {"state": "locked"|"unlocked"|"lost"|"unavailable", "reason": str, "master_offset_ns": int,
     "gm_present": bool, "gm_identity": str, "port_state": "SLAVE"|..., "timestamping":
     "software"|"hardware", "interface": str, "system_clock": {...}}   # see sysclock.system_clock
"""

from __future__ import annotations

import asyncio
import os
import re
import shutil
import tempfile
from pathlib import Path

from dcuscope.core.pycompat import ASYNC_TIMEOUTS, timeout
from dcuscope.probes.clocks.sysclock import DEFAULT_UDS, observe, system_clock
from dcuscope.protocol.ptptrust import PTP_LOCK_NS

PMC_TIMEOUT_S = 2.0
POLL_INTERVAL_S = 2.0
QUERIES = ("GET TIME_STATUS_NP", "GET PORT_DATA_SET", "GET PORT_PROPERTIES_NP")

_RESPONSE = re.compile(r"^\s*(\S+)\s+seq\s+\d+\s+RESPONSE\s+MANAGEMENT\s+(\S+)\s*$")
_FIELD = re.compile(r"^\s+(\w+)\s+(.*?)\s*$")


def parse_pmc(text: str) -> dict[str, list[dict[str, str]]]:
    """pmc's answers by TLV name (one dict per responding port), e.g.
    ``{"TIME_STATUS_NP": [{"master_offset": "-11", ...}], "PORT_DATA_SET": [...]}``.

    pmc prints ``sending: GET X`` lines between the answers and one tab-indented block per
    response; a field is any line indented under a RESPONSE header."""
    out: dict[str, list[dict[str, str]]] = {}
    block: dict[str, str] | None = None
    for line in text.splitlines():
        head = _RESPONSE.match(line)
        if head:
            block = {"_port": head.group(1)}
            out.setdefault(head.group(2), []).append(block)
        elif block is not None and line.startswith("\t\t") and (m := _FIELD.match(line)):
            block[m.group(1)] = m.group(2)
        else:
            block = None
    return out


def _slave_first(blocks: list[dict[str, str]]) -> dict[str, str]:
    """Of a boundary clock's ports, the one following a master (else the first)."""
    return next((b for b in blocks if b.get("portState") == "SLAVE"), blocks[0]) if blocks else {}


def ptp_report(answers: dict[str, list[dict[str, str]]]) -> dict:
    """The PTP part of the report from parsed pmc answers (``unavailable`` without TIME_STATUS_NP)."""
    status = (answers.get("TIME_STATUS_NP") or [{}])[0]
    if "master_offset" not in status or "gmPresent" not in status:
        return {"state": "unavailable", "reason": "no TIME_STATUS_NP answer (is ptp4l running, is its socket readable?)"}
    try:
        offset = int(status["master_offset"])
    except ValueError:
        return {"state": "unavailable", "reason": f"unreadable master_offset {status['master_offset'][:40]!r}"}
    report = {"master_offset_ns": offset, "gm_present": status["gmPresent"] == "true"}
    if "gmIdentity" in status:
        report["gm_identity"] = status["gmIdentity"]
    port = _slave_first(answers.get("PORT_DATA_SET", []))
    props = _slave_first(answers.get("PORT_PROPERTIES_NP", []))
    if "portState" in port or "portState" in props:
        report["port_state"] = port.get("portState") or props["portState"]
    if "timestamping" in props:
        report["timestamping"] = "software" if props["timestamping"] == "SOFTWARE" else "hardware"
    if "interface" in props:
        report["interface"] = props["interface"]
    locked, why = _locked(report)
    return {"state": "locked" if locked else "unlocked", "reason": why, **report}


def _locked(report: dict) -> tuple[bool, str]:
    if not report["gm_present"]:
        port = report.get("port_state")
        return False, "no grandmaster" + (f" (port {port})" if port else "")
    if report.get("port_state", "SLAVE") != "SLAVE":
        return False, f"port {report['port_state']}, not SLAVE"
    if abs(report["master_offset_ns"]) > PTP_LOCK_NS:
        return False, f"|master offset| {abs(report['master_offset_ns'])} ns above {PTP_LOCK_NS} ns"
    return True, f"slave of {report.get('gm_identity', 'the grandmaster')}"


def parse_time_status(text: str) -> dict:
    """The PTP report (without the system clock) from pmc's output."""
    return ptp_report(parse_pmc(text))


async def run_pmc(socket: str = DEFAULT_UDS, timeout_s: float = PMC_TIMEOUT_S) -> tuple[str | None, str]:
    """pmc's output for :data:`QUERIES` to the ptp4l answering at ``socket``, or (None, why not).

    pmc runs interactively: given its commands as arguments it exits once its last command got
    no answer for 100 ms, which a busy machine exceeds (answers lost); fed on stdin, it waits as
    long as stdin is open, closed here once every query got its answer or ``timeout_s`` passed.
    pmc binds a socket of its own (default ``/var/run/pmc.PID``, writable by root only): it gets
    one in a private temporary folder instead, so that a node not run as root can ask too."""
    if shutil.which("pmc") is None:
        return None, "pmc not installed (Debian package linuxptp)"
    if not os.path.exists(socket):
        return None, f"no ptp4l socket at {socket} (is ptp4l running? its uds_address?)"
    if not os.access(socket, os.W_OK):
        return None, f"no permission to write {socket} (run as root or in the socket's group, see docs/clocks.md)"
    with tempfile.TemporaryDirectory(prefix="dcuscope-pmc-") as tmp:
        try:
            proc = await asyncio.create_subprocess_exec(
                "pmc", "-u", "-b", "0", "-s", socket, "-i", str(Path(tmp) / "pmc"), stdin=asyncio.subprocess.PIPE,
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        except OSError as exc:
            return None, f"pmc failed: {exc}"
        try:
            text, err = await asyncio.wait_for(_converse(proc, timeout_s), timeout_s + 2)
        except asyncio.TimeoutError:
            proc.kill()
            await proc.wait()
            return None, "pmc timed out"
    if "RESPONSE" not in text:
        problem = err.strip().splitlines()
        return None, f"no answer from ptp4l at {socket}" + (f": {problem[-1][:120]}" if problem else "")
    return text, ""


async def _converse(proc: asyncio.subprocess.Process, timeout_s: float) -> tuple[str, str]:
    """One query at a time: pmc reads stdin with stdio, so lines written together would wait in
    its buffer, unseen by its poll, until stdin closes."""
    lines: list[str] = []
    try:
        async with timeout(timeout_s):
            for query in QUERIES:
                proc.stdin.write(f"{query}\n".encode())
                await proc.stdin.drain()
                while True:
                    line = (await proc.stdout.readline()).decode(errors="replace")
                    if not line:
                        raise TimeoutError  # pmc ended
                    lines.append(line)
                    if (head := _RESPONSE.match(line)) is not None and head.group(2) == query.split()[1]:
                        break
    except (*ASYNC_TIMEOUTS, BrokenPipeError, ConnectionResetError):
        pass  # what came is used; a missing TIME_STATUS_NP makes it "unavailable"
    proc.stdin.close()  # pmc then waits 100 ms for stragglers and exits
    rest, err = await proc.communicate()
    return "".join(lines) + rest.decode(errors="replace"), err.decode(errors="replace")


async def read_ptp_state(socket: str = DEFAULT_UDS, timeout_s: float = PMC_TIMEOUT_S) -> dict:
    """ptp4l's state via pmc and what disciplines CLOCK_REALTIME (one read, no memory)."""
    text, why = await run_pmc(socket, timeout_s)
    report = ptp_report(parse_pmc(text)) if text is not None else {"state": "unavailable", "reason": why}
    witnesses = await asyncio.to_thread(observe, report.get("interface", ""))
    report["system_clock"] = system_clock(witnesses, report.get("interface", ""), socket)
    return report


class PtpWatch:
    """Successive reads of one ptp4l, remembering whether it was locked: a port that was a
    locked slave and no longer is (grandmaster gone, port left SLAVE, ptp4l silent) is ``lost``
    until it locks again."""

    def __init__(self, socket: str = DEFAULT_UDS) -> None:
        self.socket = socket
        self._locked_to: str | None = None

    def update(self, report: dict) -> dict:
        state = report.get("state")
        if state == "locked":
            self._locked_to = report.get("gm_identity", "the grandmaster")
        elif self._locked_to is not None:
            gone = "grandmaster gone" if report.get("gm_present") is False else report.get("reason", state)
            report = dict(report, state="lost", reason=f"lost {self._locked_to}: {gone}")
        return report

    async def read(self) -> dict:
        return self.update(await read_ptp_state(self.socket))
