"""A userspace Ethernet bridge that delays every frame: the forwarding hop of bench_clock.py's
network-namespace cases, where ``tc netem`` is not available (this kernel lacks
CONFIG_NET_SCH_NETEM).

``python benchmarks/delaybridge.py IF_A IF_B --a-to-b-ms 1 --b-to-a-ms 3 --jitter-ms 0.5`` reads
every frame arriving on IF_A and IF_B (AF_PACKET sockets) and sends it out of the other one
after the delay of its direction plus a uniform jitter in [-jitter, +jitter]; a frame never
overtakes the one before it in its direction (so jitter does not reorder TCP). The bridge's
own reading and scheduling (tens of microseconds, more on a loaded machine) adds to the delay:
it is a real hop, not an exact delay line. Runs until SIGTERM.

``python benchmarks/delaybridge.py --offloads-off IF...`` first turns off the veths' checksum and
segmentation offloads (``SIOCETHTOOL``; there is no ethtool here): a frame read from a packet
socket must carry its final checksum and fit the MTU to be sent on again.

Packet sockets need root (CAP_NET_RAW); an interface it cannot open is said in one line (exit
status 2), as benchmarks/figures.py has every benchmark do.
"""

from __future__ import annotations

import argparse
import ctypes
import fcntl
import random
import select
import signal
import socket
import struct
import sys
import time
from collections import deque
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import CannotRun, run as run_main  # noqa: E402

ETH_P_ALL = 0x0003
PACKET_OUTGOING = 4
FRAME_BYTES = 65536
SIOCETHTOOL = 0x8946
OFFLOADS = {"tx-checksum": 0x17, "tso": 0x1F, "gso": 0x24, "gro": 0x2C}
"""ETHTOOL_S* commands of the legacy ethtool_value interface."""


def offloads_off(name: str) -> None:
    for cmd in OFFLOADS.values():
        value = ctypes.create_string_buffer(struct.pack("II", cmd, 0))
        ifreq = struct.pack("16sP", name.encode(), ctypes.addressof(value)).ljust(40, b"\0")
        with socket.socket() as s:
            try:
                fcntl.ioctl(s, SIOCETHTOOL, ifreq)
            except OSError as exc:
                raise CannotRun(f"cannot turn off the offloads of {name}: {exc.strerror}") from exc


def open_interface(name: str) -> socket.socket:
    try:
        s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        s.bind((name, 0))
    except OSError as exc:  # EPERM without CAP_NET_RAW, ENODEV for an unknown interface
        raise CannotRun(f"cannot open a packet socket on {name}: {exc.strerror}") from exc
    s.setblocking(False)
    return s


class Direction:
    """Frames read on ``src``, due out of ``dst`` after ``delay_s`` +- ``jitter_s``, in order."""

    def __init__(self, src: socket.socket, dst: socket.socket, delay_s: float, jitter_s: float) -> None:
        self.src, self.dst, self.delay_s, self.jitter_s = src, dst, delay_s, jitter_s
        self.queue: deque[tuple[float, bytes]] = deque()
        self.last_due = 0.0
        self.forwarded = 0

    def read(self) -> None:
        while True:
            try:
                frame, addr = self.src.recvfrom(FRAME_BYTES)
            except BlockingIOError:
                return
            if addr[2] == PACKET_OUTGOING:  # what this bridge itself sent out of src
                continue
            due = time.monotonic() + max(0.0, self.delay_s + random.uniform(-self.jitter_s, self.jitter_s))
            self.last_due = max(self.last_due, due)
            self.queue.append((self.last_due, frame))

    def send_due(self, now: float) -> None:
        while self.queue and self.queue[0][0] <= now:
            _, frame = self.queue.popleft()
            try:
                self.dst.send(frame)
                self.forwarded += 1
            except OSError:  # a frame the other side cannot take (too big): dropped, as a switch would
                pass

    def wait_s(self, now: float) -> float | None:
        return max(0.0, self.queue[0][0] - now) if self.queue else None


def run(a: str, b: str, a_to_b_s: float, b_to_a_s: float, jitter_s: float) -> None:
    sa, sb = open_interface(a), open_interface(b)
    dirs = {sa: Direction(sa, sb, a_to_b_s, jitter_s), sb: Direction(sb, sa, b_to_a_s, jitter_s)}
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    print(f"delaybridge: {a} -> {b} {a_to_b_s * 1e3:g} ms, {b} -> {a} {b_to_a_s * 1e3:g} ms, "
          f"jitter +-{jitter_s * 1e3:g} ms", flush=True)
    while not stop:
        now = time.monotonic()
        waits = [w for w in (d.wait_s(now) for d in dirs.values()) if w is not None]
        try:
            readable, _, _ = select.select(list(dirs), [], [], min(waits, default=0.5))
        except InterruptedError:
            continue
        for s in readable:
            dirs[s].read()
        now = time.monotonic()
        for d in dirs.values():
            d.send_due(now)


def main(argv: list[str] | None = None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["--offloads-off"]:
        for name in argv[1:]:
            offloads_off(name)
        return 0
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--a-to-b-ms", type=float, default=0.0)
    p.add_argument("--b-to-a-ms", type=float, default=0.0)
    p.add_argument("--jitter-ms", type=float, default=0.0)
    args = p.parse_args(argv)
    run(args.a, args.b, args.a_to_b_ms / 1e3, args.b_to_a_ms / 1e3, args.jitter_ms / 1e3)
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
