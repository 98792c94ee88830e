"""Issue 50's prototypes: the relay's live hot loop done three ways, measured side by side in one run
(CPU time per event and per batch, in-process, the paper's pace: R paced DCUs at 4,300 events/s in
batches of ~176 events, pushes at 30 ticks a second for a page showing every DCU).

- ``numpy merge``: the relay before issue 50: each batch decoded from its wire bytes
  (``decode_batch``), queued in its run (``LiveRun.add``); each tick every run merged with numpy
  (``LiveRun._merge``: open frames found or opened, cells scatter-min'd, a few dozen numpy calls),
  judged (``maintain_all``) and its newly shown frames' columns corrected for the push
  (``framepack.corrected``).
- ``compiled merge``: the same with each batch merged by one compiled pass over its records
  (``model/c/merge.c``: an open-addressing hash of the frame keys), as relays do since.
  Judging, showing, finalising and pushing stay the delay model's numpy.
- ``node pairs`` (and ``node pairs, compiled``, the node merging with the compiled pass): each node
  runs the live engine on its own events and ships its newly shown frames' columns
  (``framepack.node_columns``, what a push carries) instead of events; the relay appends them and
  corrects them per push. Its two halves are measured apart: the node's shipping thread (pair,
  judge, encode: CPU per event of the node's own events, a goal of at most 1 µs) and the relay's
  (decode, append, push). The relay half is a lower bound: finalised frames' statistics, the store
  and fleet rows are left out of it.

``--floor``: the per-message cost of any relay written in Python with aiohttp, whatever it does with
a batch: a server that receives binary messages of a paced batch's size on a real WebSocket and
answers each with an acknowledgement of the relay's shape, fed by N clients in another process;
the server's CPU per message from ``/proc``.

    .venv/bin/python benchmarks/proto_live_path.py --runs 8 --seconds 8 --rounds 3
    .venv/bin/python benchmarks/proto_live_path.py --floor --clients 8 --messages 4000
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dcuscope.probes.ship.simnode import EVENTS_PER_FRAME, header_for, synth_events  # noqa: E402
from dcuscope.protocol.wire import decode_batch, encode_batch  # noqa: E402
from dcuscope.relay.clock.correction import Correction, Segment  # noqa: E402
from dcuscope.relay.live import framepack  # noqa: E402
from dcuscope.model import compiled as cmerge  # noqa: E402
from dcuscope.relay.live.run import PUSHED_FRAMES, Grow, LiveRun, maintain_all  # noqa: E402

RATE = 4300.0
SOURCES = 2
BATCH_S = 0.040
"""A paced node ships a batch every 40 ms (probes/ship/relayexport.py, adaptive)."""
T0 = 1_700_000_000_000_000_000
RUN_ID = "0" * 31 + "1"


# --- the hot loop, three ways -------------------------------------------------------------------

def _setup(runs: int, seconds: float):
    fps = RATE / (EVENTS_PER_FRAME * SOURCES)
    corr = Correction("estimate", "bench", (Segment(from_ns=0, ref_ns=T0, offset_ns=1000, drift_ppb=20, uncertainty_ns=20000),))
    events = [synth_events(int(fps * (seconds + 3)), SOURCES, fps, T0 + r * 1_000_000, seed=r) for r in range(runs)]
    return corr, events


def _batches(ev: np.ndarray, start: int, end: int) -> list[tuple[int, np.ndarray]]:
    """The batches a paced node ships from node time ``start`` to ``end``: (the time it ships, events)."""
    out = []
    for t in range(start, end, int(BATCH_S * 1e9)):
        a, b = np.searchsorted(ev["ts"], [t, t + int(BATCH_S * 1e9)])
        if b > a:
            out.append((t + int(BATCH_S * 1e9), ev[a:b]))
    return out


def _warm(live: list[LiveRun], events: list[np.ndarray], seconds: float) -> list[list[tuple[int, np.ndarray]]]:
    """Each run fed its node's first second (the open table and the rings fill); returns the batches
    each node ships in the ``seconds`` after it."""
    warm, end = T0 + 1_000_000_000, T0 + int((seconds + 1) * 1e9)
    after = []
    for run, ev in zip(live, events):
        for _, b in _batches(ev, T0, warm):
            run.add(b)
        run.maintain()
        after.append(_batches(ev, warm, end))
    return after


def relay_loop(way: str, runs: int, seconds: float, hz: float) -> dict:
    """``numpy merge`` or ``compiled merge``: the relay's CPU from wire bytes to pushed columns."""
    corr, events = _setup(runs, seconds)
    header = header_for("DCU", SOURCES, T0)
    live = [LiveRun(header, budget=64 << 20, compiled=way == "compiled merge") for _ in range(runs)]
    warm, end = T0 + 1_000_000_000, T0 + int((seconds + 1) * 1e9)
    wires = [[(t, encode_batch(RUN_ID, k, b, compress=True)) for k, (t, b) in enumerate(plan)]
             for plan in _warm(live, events, seconds)]
    pushed = [run.visible for run in live]
    at = [0] * runs
    step, t, n_events, n_batches = int(1e9 / hz), warm, 0, 0
    cpu = time.process_time()
    while t < end:
        t += step
        for k, run in enumerate(live):
            w = wires[k]
            while at[k] < len(w) and w[at[k]][0] <= t:
                batch = decode_batch(w[at[k]][1], len(run.stages))
                run.add(batch.events)
                n_events += len(batch.events)
                n_batches += 1
                at[k] += 1
        maintain_all(live)
        for k, run in enumerate(live):
            if run.visible > pushed[k]:
                framepack.corrected(*run.recent_columns(pushed[k], 500), corr, len(run.stages))
                pushed[k] = run.visible
    cpu = time.process_time() - cpu
    return {"way": way, "side": "relay", "events": n_events, "batches": n_batches, "cpu_s": cpu,
            "frames": sum(run.visible for run in live)}


def node_loop(way: str, runs: int, seconds: float) -> dict:
    """``node pairs``, the node's half: each node pairs and judges its own batches as it ships them
    and encodes the columns of the frames newly shown (``node pairs, compiled``: merged by the
    compiled pass). Returns the node's CPU and the messages."""
    corr, events = _setup(runs, seconds)
    header = header_for("DCU", SOURCES, T0)
    live = [LiveRun(header, budget=16 << 20, compiled=way.endswith("compiled")) for _ in range(runs)]
    plans = _warm(live, events, seconds)
    sent = [run.visible for run in live]
    messages: list[list[tuple[int, bytes]]] = [[] for _ in live]
    n_events = 0
    cpu = time.process_time()
    for k, (run, plan) in enumerate(zip(live, plans)):
        for t, b in plan:
            run.add(b)
            run.maintain()
            n_events += len(b)
            ints, floats = run.recent_columns(sent[k], PUSHED_FRAMES)
            sent[k] = run.visible
            messages[k].append((t, np.ascontiguousarray(ints.T).tobytes() + np.ascontiguousarray(floats.T).tobytes()))
    cpu = time.process_time() - cpu
    return {"way": way, "side": "node", "events": n_events, "batches": sum(len(p) for p in plans), "cpu_s": cpu,
            "frames": sum(run.visible for run in live), "messages": messages, "corr": corr}


def relay_of_frames(node: dict, seconds: float, hz: float) -> dict:
    """``node pairs``, the relay's half: per message the frames' columns decoded and appended; per
    tick the new ones corrected for the push."""
    messages, corr, stages = node["messages"], node["corr"], len(header_for("DCU", SOURCES, T0).stages)
    ni, nf = framepack.int_rows(stages), framepack.float_rows(stages)
    row = (ni + nf) * 8
    kept = [{"ints": Grow(np.int64, (ni,), PUSHED_FRAMES), "floats": Grow(np.float64, (nf,), PUSHED_FRAMES)} for _ in messages]
    at, shown = [0] * len(messages), [0] * len(messages)
    warm, end = T0 + 1_000_000_000, T0 + int((seconds + 1) * 1e9)
    step, t, n_batches = int(1e9 / hz), warm, 0
    cpu = time.process_time()
    while t < end:
        t += step
        for k, m in enumerate(messages):
            while at[k] < len(m) and m[at[k]][0] <= t:
                data = m[at[k]][1]
                n = len(data) // row
                kept[k]["ints"].extend(np.frombuffer(data, np.int64, n * ni).reshape(n, ni))
                kept[k]["floats"].extend(np.frombuffer(data, np.float64, n * nf, n * ni * 8).reshape(n, nf))
                shown[k] += n
                at[k] += 1
                n_batches += 1
        for k, g in enumerate(kept):
            if shown[k]:
                framepack.corrected(g["ints"].view[-shown[k]:].T, g["floats"].view[-shown[k]:].T, corr, stages)
                shown[k] = 0
    cpu = time.process_time() - cpu
    return {"way": node["way"], "side": "relay", "events": node["events"], "batches": n_batches, "cpu_s": cpu,
            "frames": node["frames"]}


def measure(way: str, runs: int, seconds: float, hz: float) -> list[dict]:
    if "compiled" in way and cmerge.load() is None:
        raise SystemExit(f"proto_live_path: no compiled merge ({cmerge.unavailable_reason()})")
    if way.startswith("node pairs"):
        node = node_loop(way, runs, seconds)
        relay = relay_of_frames(node, seconds, hz)
        del node["messages"], node["corr"]
        return [node, relay]
    return [relay_loop(way, runs, seconds, hz)]


# --- the per-message floor ----------------------------------------------------------------------

FLOOR_SERVER = r"""
import asyncio, json, sys
from aiohttp import web, WSMsgType
async def ingest(request):
    ws = web.WebSocketResponse(max_msg_size=4 << 20)
    await ws.prepare(request)
    async for msg in ws:
        if msg.type == WSMsgType.BINARY:
            seq = int.from_bytes(msg.data[24:32], "little")
            await ws.send_str(json.dumps({"v": 2, "type": "ack", "seq": seq, "ok": True}))
    return ws
app = web.Application(); app.router.add_get("/ingest", ingest)
web.run_app(app, host="127.0.0.1", port=int(sys.argv[1]), print=None)
"""

FLOOR_CLIENTS = r"""
import asyncio, sys, aiohttp
port, clients, messages, size = map(int, sys.argv[1:5])
async def one(session):
    async with session.ws_connect(f"http://127.0.0.1:{port}/ingest") as ws:
        body = bytearray(size)
        for k in range(messages):
            body[24:32] = k.to_bytes(8, "little")
            await ws.send_bytes(bytes(body))
            await ws.receive()
async def main():
    async with aiohttp.ClientSession() as session:
        await asyncio.gather(*(one(session) for _ in range(clients)))
asyncio.run(main())
"""


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def floor(clients: int, messages: int, size: int) -> dict:
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-c", FLOOR_SERVER, str(port)])
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), 0.2).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise SystemExit("proto_live_path: the floor's server did not start")
                time.sleep(0.05)
        before = _cpu_s(server.pid)
        subprocess.run([sys.executable, "-c", FLOOR_CLIENTS, str(port), str(clients), str(messages), str(size)],
                       check=True, timeout=300)
        cpu = _cpu_s(server.pid) - before
    finally:
        server.terminate()
        server.wait(10)
    n = clients * messages
    return {"messages": n, "cpu_s": cpu, "us_per_message": 1e6 * cpu / n}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--runs", type=int, default=8, help="paced DCUs (default 8)")
    p.add_argument("--seconds", type=float, default=8.0, help="node time measured (default 8)")
    p.add_argument("--hz", type=float, default=30.0, help="push ticks a second (default 30)")
    p.add_argument("--rounds", type=int, default=2, help="times each way runs, in turn (default 2)")
    p.add_argument("--floor", action="store_true", help="measure the per-message floor of an aiohttp relay instead")
    p.add_argument("--clients", type=int, default=8, help="--floor: connections (default 8)")
    p.add_argument("--messages", type=int, default=4000, help="--floor: messages a connection (default 4000)")
    p.add_argument("--size", type=int, default=1900, help="--floor: bytes a message (default 1900: a paced batch, zlib)")
    p.add_argument("--quick", action="store_true", help="2 DCUs, 2 s, 1 round (or a short floor): the output's shape")
    p.add_argument("--inner", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.quick:
        args.runs, args.seconds, args.rounds, args.clients, args.messages = 2, 2.0, 1, 2, 200
    if args.floor:
        f = floor(args.clients, args.messages, args.size)
        print(f"aiohttp WebSocket, receive + ack, {f['messages']:,} messages of {args.size} bytes over {args.clients} "
              f"connections: {f['us_per_message']:.1f} µs of server CPU per message "
              f"({f['us_per_message'] / 176:.2f} µs per event at 176 events a batch)")
        return 0
    if args.inner:
        print(json.dumps(measure(args.inner, args.runs, args.seconds, args.hz)))
        return 0
    if cmerge.load() is None:
        print(f"proto_live_path: the compiled merge is unavailable ({cmerge.unavailable_reason()})", file=sys.stderr)
        return 2
    ways = ("numpy merge", "compiled merge", "node pairs", "node pairs, compiled")
    results: dict[tuple[str, str], list[dict]] = {}
    for _ in range(args.rounds):
        for way in ways:
            out = subprocess.run([sys.executable, __file__, "--inner", way, "--runs", str(args.runs), "--seconds",
                                  str(args.seconds), "--hz", str(args.hz)], capture_output=True, text=True, check=False)
            if out.returncode != 0:
                sys.exit(f"proto_live_path: {way} failed: {out.stderr.strip()[-2000:]}")
            for r in json.loads(out.stdout.strip().splitlines()[-1]):
                results.setdefault((r["way"], r["side"]), []).append(r)
    print(f"{args.runs} paced DCUs, {args.hz:g} push ticks/s, {args.seconds:g} s of node time, {args.rounds} rounds")
    print(f"  {'way':<20} {'where':<6} {'µs/event':>9} {'µs/batch':>9} {'frames':>8}   per round (µs/event)")
    base = None
    for (way, side), rs in results.items():
        cpu, ev, b = sum(r["cpu_s"] for r in rs), sum(r["events"] for r in rs), sum(r["batches"] for r in rs)
        per_event = 1e6 * cpu / ev
        base = base or per_event
        rounds = ", ".join(f"{1e6 * r['cpu_s'] / r['events']:.2f}" for r in rs)
        print(f"  {way:<20} {side:<6} {per_event:9.2f} {1e6 * cpu / b:9.0f} {rs[-1]['frames']:8,}   {rounds}"
              f"{'' if side == 'node' else f'  ({base / per_event:.2f}× the numpy merge)'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
