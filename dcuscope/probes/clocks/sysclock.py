"""What disciplines this machine's CLOCK_REALTIME (the clock the probes read), read-only.

Three witnesses, none of which changes anything:

- the kernel's NTP state, ``adjtimex`` with ``modes = 0`` (a pure read): ``STA_UNSYNC`` set means
  no daemon has declared the clock synchronised. phc2sys and a ptp4l that steers CLOCK_REALTIME
  clear it with every locked update (linuxptp's ``sysclk_set_sync``: status and maxerror only,
  never esterror); chronyd and ntpd also maintain ``esterror``, the error they estimate;
- the running processes (``/proc/*/cmdline``): phc2sys and its source clock, ptp4l with its
  timestamping and ``free_running`` (from its arguments and its ``-f`` config file), chronyd,
  ntpd, systemd-timesyncd;
- ``chronyc -n tracking`` where chronyc exists: a reference named ``PHC...`` is a PTP hardware
  clock refclock, i.e. chrony follows PTP.

A node in a container sees only its own processes; adjtimex still tells whether the clock is
synchronised, and the detail says that no daemon was seen.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import re
import shlex
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

STA_UNSYNC = 0x0040
DEFAULT_UDS = "/var/run/ptp4l"
"""linuxptp's default ``uds_address``: where ptp4l answers pmc and phc2sys."""
CHRONYC_TIMEOUT_S = 2.0
DAEMONS = ("phc2sys", "ptp4l", "chronyd", "ntpd", "systemd-timesyncd")


class _Timeval(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long)]


class _Timex(ctypes.Structure):
    """glibc's ``struct timex`` (sys/timex.h), padding included."""
    _fields_ = [("modes", ctypes.c_uint), ("offset", ctypes.c_long), ("freq", ctypes.c_long),
                ("maxerror", ctypes.c_long), ("esterror", ctypes.c_long), ("status", ctypes.c_int),
                ("constant", ctypes.c_long), ("precision", ctypes.c_long), ("tolerance", ctypes.c_long),
                ("time", _Timeval), ("tick", ctypes.c_long), ("ppsfreq", ctypes.c_long),
                ("jitter", ctypes.c_long), ("shift", ctypes.c_int), ("stabil", ctypes.c_long),
                ("jitcnt", ctypes.c_long), ("calcnt", ctypes.c_long), ("errcnt", ctypes.c_long),
                ("stbcnt", ctypes.c_long), ("tai", ctypes.c_int), ("_pad", ctypes.c_int * 11)]


@dataclass(frozen=True)
class KernelClock:
    """The kernel's view of CLOCK_REALTIME (adjtimex)."""
    status: int
    maxerror_us: int
    esterror_us: int
    freq_ppm: float

    @property
    def synced(self) -> bool:
        return not self.status & STA_UNSYNC


def read_adjtimex() -> KernelClock | None:
    """adjtimex with modes 0 (reads, never sets); None where libc or the call is unavailable."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    tx = _Timex()  # zeroed: modes = 0 is a read
    if ctypes.CDLL(name, use_errno=True).adjtimex(ctypes.byref(tx)) < 0:
        return None
    return KernelClock(tx.status, tx.maxerror, tx.esterror, tx.freq / 65536.0)


# --- processes --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Proc:
    pid: int
    name: str
    """The program's base name (argv[0]'s, which is what ``comm`` truncates to 15 characters)."""
    argv: tuple[str, ...]


def running_daemons(proc: Path = Path("/proc")) -> list[Proc]:
    """The clock daemons among the processes this node can see."""
    found = []
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            raw = (entry / "cmdline").read_bytes()
        except OSError:  # gone meanwhile, or not ours to read
            continue
        argv = tuple(a.decode(errors="replace") for a in raw.split(b"\0") if a)
        name = Path(argv[0]).name if argv else ""
        if name in DAEMONS:
            found.append(Proc(int(entry.name), name, argv))
    return sorted(found, key=lambda p: p.pid)


def _options(argv: tuple[str, ...], with_value: str) -> dict[str, list[str]]:
    """Short options (``-s eth0``, ``-seth0``, flags) and long ones (``--name value``) of argv[1:]."""
    out: dict[str, list[str]] = {}
    args = list(argv[1:])
    while args:
        a = args.pop(0)
        if a.startswith("--") and len(a) > 2:
            key, _, value = a[2:].partition("=")
            out.setdefault(key, []).append(value if _ else (args.pop(0) if args else ""))
        elif a.startswith("-") and len(a) > 1:
            letters = a[1:]
            while letters:
                key, letters = letters[0], letters[1:]
                if key in with_value:
                    out.setdefault(key, []).append(letters or (args.pop(0) if args else ""))
                    break
                out.setdefault(key, []).append("")
    return out


@dataclass(frozen=True)
class Ptp4lSetup:
    """What a ptp4l process was started with: which clock it steers, whom it answers."""
    pid: int
    uds: str
    software: bool
    free_running: bool
    interfaces: tuple[str, ...] = field(default=())


def ptp4l_setup(p: Proc) -> Ptp4lSetup:
    """Command-line options override the ``-f`` config file's ``[global]`` section, as in ptp4l."""
    opts = _options(p.argv, "fimplsq")
    conf: dict[str, str] = {}
    if opts.get("f"):
        try:
            conf = config_globals(Path(opts["f"][-1]).read_text())
        except OSError:
            conf = {}
    conf.update({k: v[-1] for k, v in opts.items() if len(k) > 1})
    flags = [k for k in opts if k in "SHL"]
    software = flags[-1] == "S" if flags else conf.get("time_stamping", "hardware") == "software"
    return Ptp4lSetup(p.pid, conf.get("uds_address", DEFAULT_UDS), software,
                      conf.get("free_running", "0").strip() == "1", tuple(opts.get("i", ())))


def config_globals(text: str) -> dict[str, str]:
    """``key value`` lines of a linuxptp config's ``[global]`` section (comments dropped)."""
    out, section = {}, "global"
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1].strip()
        elif section == "global":
            key, _, value = line.partition(" ")
            out[key] = value.strip()
    return out


def phc2sys_source(p: Proc) -> str | None:
    """The clock a phc2sys process steers CLOCK_REALTIME from (``auto`` for ``-a -r``), or None
    when it does not steer CLOCK_REALTIME (e.g. the grandmaster's ``-s CLOCK_REALTIME -c eth0``)."""
    opts = _options(p.argv, "cdsiOERPIlLMNtuzfmqnx")
    if "a" in opts:
        return "auto" if "r" in opts else None
    sink = (opts.get("c") or ["CLOCK_REALTIME"])[-1]
    source = (opts.get("s") or opts.get("i") or opts.get("d") or [""])[-1]
    if sink != "CLOCK_REALTIME" or not source or source == "CLOCK_REALTIME":
        return None
    return source


def phc_devices(interface: str, sysfs: Path = Path("/sys/class/net")) -> set[str]:
    """``/dev/ptpN`` of ``interface``'s hardware clock (none with software timestamping)."""
    return {f"/dev/{d.name}" for d in (sysfs / interface / "device" / "ptp").glob("ptp*")} if interface else set()


# --- chrony -----------------------------------------------------------------------------------

_REFERENCE = re.compile(r"^Reference ID\s*:\s*(\S+)\s*\(([^)]*)\)", re.MULTILINE)
_LEAP = re.compile(r"^Leap status\s*:\s*(.+?)\s*$", re.MULTILINE)


def parse_chrony_tracking(text: str) -> dict:
    """``chronyc -n tracking``: reference name, whether it is a PHC refclock, synchronised or not."""
    ref, leap = _REFERENCE.search(text), _LEAP.search(text)
    name = ref.group(2) if ref else ""
    return {"reference": name, "phc": name.upper().startswith(("PHC", "PTP")),
            "synced": bool(leap) and leap.group(1) != "Not synchronised"}


def chrony_tracking() -> dict | None:
    if shutil.which("chronyc") is None:
        return None
    try:
        out = subprocess.run(["chronyc", "-n", "tracking"], capture_output=True, text=True,
                             timeout=CHRONYC_TIMEOUT_S).stdout
    except (OSError, subprocess.TimeoutExpired):
        return None
    return parse_chrony_tracking(out)


def quote(argv: tuple[str, ...]) -> str:
    return shlex.join((Path(argv[0]).name,) + argv[1:])[:120]


# --- the verdict ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Witnesses:
    """Everything read about the system clock at one moment (see :func:`observe`)."""
    kernel: KernelClock | None
    daemons: tuple[Proc, ...]
    chrony: dict | None = None
    phcs: frozenset[str] = frozenset()
    """``/dev/ptpN`` of the PTP port's interface."""


def observe(interface: str) -> Witnesses:
    daemons = tuple(running_daemons())
    chrony = chrony_tracking() if any(p.name == "chronyd" for p in daemons) else None
    return Witnesses(read_adjtimex(), daemons, chrony, frozenset(phc_devices(interface)))


def system_clock(w: Witnesses, interface: str, uds: str) -> dict:
    """The ``system_clock`` part of the node's PTP report: synchronised (kernel), by what, and
    whether that follows the PTP port of ``interface`` answering at ``uds``."""
    out: dict = {"synced": w.kernel.synced if w.kernel else False}
    if w.kernel is not None:
        out.update(maxerror_us=w.kernel.maxerror_us, esterror_us=w.kernel.esterror_us,
                   freq_ppm=round(w.kernel.freq_ppm, 3))
    by, follows, detail = _steering(w, interface, uds)
    out.update(by=by, follows_ptp=follows, detail=detail if w.kernel else f"{detail}; adjtimex unreadable")
    return out


def _steering(w: Witnesses, interface: str, uds: str) -> tuple[str | None, bool, str]:
    """(daemon steering CLOCK_REALTIME, follows our PTP port, one-line detail)."""
    notes = []
    steering = []
    for p in w.daemons:
        if p.name != "phc2sys" or (source := phc2sys_source(p)) is None:
            continue
        auto_uds = (_options(p.argv, "cdsiOERPIlLMNtuzfmqnx").get("z") or [DEFAULT_UDS])[-1]
        if (source == "auto" and auto_uds == uds) or (source != "auto" and (source == interface or source in w.phcs)):
            return "phc2sys", True, f"phc2sys steers it from this port's clock ({quote(p.argv)})"
        origin = f"the ptp4l at {auto_uds}" if source == "auto" else source
        steering.append(("phc2sys", f"phc2sys steers it from {origin}, not from {interface or 'the PTP port'}"))
    for setup in (ptp4l_setup(p) for p in w.daemons if p.name == "ptp4l"):
        if setup.uds != uds:
            continue
        if setup.software and not setup.free_running:
            return "ptp4l", True, "ptp4l steers it (software timestamping)"
        notes.append("ptp4l free_running" if setup.free_running else "ptp4l steers only its NIC's hardware clock")
    if not steering:
        notes.append("no phc2sys")
    if w.chrony is not None:
        if w.chrony["phc"]:
            return "chrony", True, f"chrony follows PTP hardware clock refclock {w.chrony['reference']}"
        steering.append(("chrony", f"chrony follows {w.chrony['reference'] or 'no reference'}"))
    for name, by in (("chronyd", "chrony"), ("ntpd", "ntpd"), ("systemd-timesyncd", "timesyncd")):
        if any(p.name == name for p in w.daemons) and not any(s[0] == by for s in steering):
            steering.append((by, f"{name} steers it"))
    if not steering and not w.daemons:
        notes.append("no clock daemon seen")
    return (steering[0][0] if steering else None), False, ", ".join(notes + [s[1] for s in steering])
