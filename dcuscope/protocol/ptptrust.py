"""What a node's PTP report is worth: whether its timestamps may be taken as on the grandmaster's
clock, and the bound on their error. The node reads and reports its PTP state
(:mod:`dcuscope.probes.clocks.ptp`); the relay judges the report with these, so both sides agree
on what "locked" means."""

from __future__ import annotations

PTP_LOCK_NS = 100_000
"""|master_offset| under which a slave port with a grandmaster counts as locked. Locked
software timestamping holds a few µs, hardware well under 1 µs; the bound is loose so that a
jittery software path does not flip the node between trusted and estimated every poll. The
uncertainty stated while trusted is |master_offset| itself (plus the system clock's stated
error), so a loose bound costs no honesty."""


def ptp_trusted(ptp: dict) -> tuple[bool, str]:
    """Whether node timestamps may be taken as on the grandmaster's clock, and in one line why (not).

    Trusted only when the port is a locked slave of a present grandmaster *and* CLOCK_REALTIME
    (what the probes read) is synchronised and follows that PTP port."""
    if not isinstance(ptp, dict) or ptp.get("state") != "locked":
        state = ptp.get("state", "unavailable") if isinstance(ptp, dict) else "unavailable"
        reason = ptp.get("reason") if isinstance(ptp, dict) else None
        return False, f"PTP {state}" + (f" ({reason})" if reason else "")
    if ptp.get("gm_present") is not True or ptp.get("port_state", "SLAVE") != "SLAVE":
        return False, f"PTP port {ptp.get('port_state', '?')}, grandmaster present: {ptp.get('gm_present')}"
    offset = ptp.get("master_offset_ns")
    if not isinstance(offset, int) or abs(offset) > PTP_LOCK_NS:
        return False, f"PTP master offset {offset} ns beyond {PTP_LOCK_NS} ns"
    clock = ptp.get("system_clock")
    if not isinstance(clock, dict):
        return False, "ptp4l locked but the node did not say what disciplines CLOCK_REALTIME"
    if not clock.get("follows_ptp"):
        return False, f"ptp4l locked but CLOCK_REALTIME not disciplined by PTP ({clock.get('detail') or 'nothing follows it'})"
    if not clock.get("synced"):
        return False, f"ptp4l locked, {clock.get('by')} runs, but CLOCK_REALTIME is unsynchronised (adjtimex STA_UNSYNC)"
    return True, f"PTP locked to {ptp.get('gm_identity', 'the grandmaster')}, offset {offset} ns, CLOCK_REALTIME by {clock.get('by')}"


STATED_ERROR_BY = ("chrony", "ntpd")
"""Daemons that keep adjtimex's esterror up to date; phc2sys and ptp4l leave it untouched (a
stale or boot-time 16 s) and reset maxerror to 0 each update (it then grows 500 ppm, a kernel
bound, not an error estimate)."""


def ptp_uncertainty_ns(ptp: dict) -> int:
    """Bound on a trusted node's clock error: |master_offset| plus the system clock's stated
    error where its daemon states one (chrony, ntpd: adjtimex esterror)."""
    offset = ptp.get("master_offset_ns")
    unc = abs(offset) if isinstance(offset, int) and not isinstance(offset, bool) else 0
    clock = ptp.get("system_clock")
    if isinstance(clock, dict) and clock.get("by") in STATED_ERROR_BY and isinstance(clock.get("esterror_us"), int):
        unc += clock["esterror_us"] * 1000
    return unc
