"""A slow, lossy UDP link for tests, in user space: every datagram that reaches ``--listen`` is sent
on to ``--to`` ``--delay-ms`` later, unless it is one of the ``--loss`` fraction dropped at random.

This machine's kernel has no ``sch_netem`` (``tc qdisc add ... netem``: "Specified qdisc kind is
unknown"), so the delay netem would add is added here, between two real sockets. What it did is
the ground truth: one JSON line per datagram on ``--log`` with its RTP SSRC, timestamp and
sequence number, when it came (the kernel's receive timestamp, SO_TIMESTAMPNS: not when this
process woke up to read it) and when it left (CLOCK_REALTIME ns; ``null``: dropped).

    python -m tests.delayline --listen 10.79.0.2:5700 --to 127.0.0.1:5600 --delay-ms 20 --loss 0.25 \\
        --log line.jsonl --seconds 12
"""

from __future__ import annotations

import argparse
import heapq
import json
import random
import select
import socket
import struct
import time


SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
"""Linux's value where Python does not name it."""


def _kernel_time(ancillary: list) -> int:
    """The receive time the kernel stamped on a datagram (CLOCK_REALTIME ns), else now."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= 16:
            seconds, nanoseconds = struct.unpack("qq", data[:16])
            return seconds * 1_000_000_000 + nanoseconds
    return time.clock_gettime_ns(time.CLOCK_REALTIME)


def _addr(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--listen", type=_addr, required=True)
    p.add_argument("--to", type=_addr, required=True)
    p.add_argument("--delay-ms", type=float, required=True)
    p.add_argument("--loss", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--log", required=True)
    p.add_argument("--seconds", type=float, required=True, help="how long it runs (bounded: a test's helper)")
    args = p.parse_args(argv)
    rng = random.Random(args.seed)
    delay_ns = round(args.delay_ms * 1e6)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    rx.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    rx.bind(args.listen)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    held: list[tuple[int, int, bytes, dict]] = []
    order = 0
    end = time.monotonic() + args.seconds
    with open(args.log, "w", buffering=1) as log:  # line by line: a test may end it while it runs
        print("listening", flush=True)
        while time.monotonic() < end or held:
            wait = 0.05 if not held else max(0.0, (held[0][0] - time.clock_gettime_ns(time.CLOCK_REALTIME)) / 1e9)
            ready, _, _ = select.select([rx], [], [], min(wait, 0.05))
            if ready and time.monotonic() < end:
                data, ancillary, _, _ = rx.recvmsg(65536, socket.CMSG_SPACE(16))
                now = _kernel_time(ancillary)
                entry = {"in": now, "out": None}
                if len(data) >= 12:
                    seq, rtptime, ssrc = struct.unpack("!HII", data[2:12])
                    entry.update(seq=seq, rtptime=rtptime, ssrc=ssrc)
                if rng.random() < args.loss:
                    log.write(json.dumps(entry) + "\n")
                else:
                    heapq.heappush(held, (now + delay_ns, order, data, entry))
                    order += 1
            now = time.clock_gettime_ns(time.CLOCK_REALTIME)
            while held and held[0][0] <= now:
                _, _, data, entry = heapq.heappop(held)
                tx.sendto(data, args.to)
                entry["out"] = time.clock_gettime_ns(time.CLOCK_REALTIME)
                log.write(json.dumps(entry) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
