"""The node's PTP state, read from linuxptp's ``pmc``: is this machine's clock following a grandmaster?"""

from __future__ import annotations

import asyncio
import re
import shutil

PTP_LOCK_NS = 100_000
"""|master_offset| under which a node with a grandmaster present counts as PTP-locked."""
PMC_COMMAND = ("pmc", "-u", "-b", "0", "GET TIME_STATUS_NP")

_FIELD = re.compile(r"^\s*(master_offset|gmPresent|gmIdentity)\s+(\S+)\s*$", re.MULTILINE)


def parse_time_status(text: str) -> dict:
    """PTP state from ``pmc ... 'GET TIME_STATUS_NP'`` output (``unavailable`` if it holds none).

    TIME_STATUS_NP tells how ptp4l's hardware clock follows the grandmaster; that
    CLOCK_REALTIME follows that hardware clock is phc2sys's job, which pmc cannot see.
    """
    fields = dict(_FIELD.findall(text))
    if "master_offset" not in fields or "gmPresent" not in fields:
        return {"state": "unavailable", "reason": "no TIME_STATUS_NP response (is ptp4l running?)"}
    try:
        offset = int(fields["master_offset"])
    except ValueError:
        return {"state": "unavailable", "reason": "unreadable master_offset"}
    present = fields["gmPresent"] == "true"
    locked = present and abs(offset) <= PTP_LOCK_NS
    state = {"state": "locked" if locked else "unlocked", "master_offset_ns": offset, "gm_present": present}
    if "gmIdentity" in fields:
        state["gm_identity"] = fields["gmIdentity"]
    return state


async def read_ptp_state(timeout_s: float = 2.0) -> dict:
    """The local PTP state via linuxptp's ``pmc``; ``unavailable`` where pmc or ptp4l is missing."""
    if shutil.which(PMC_COMMAND[0]) is None:
        return {"state": "unavailable", "reason": "pmc not installed"}
    try:
        proc = await asyncio.create_subprocess_exec(
            *PMC_COMMAND, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
    except OSError as exc:
        return {"state": "unavailable", "reason": f"pmc failed: {exc}"}
    try:
        out, _ = await asyncio.wait_for(proc.communicate(), timeout_s)
    except asyncio.TimeoutError:
        proc.kill()
        await proc.wait()
        return {"state": "unavailable", "reason": "pmc timed out"}
    return parse_time_status(out.decode(errors="replace"))
