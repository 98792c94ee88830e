"""The compiled floor: what the compiled core alone costs per event, in this process. Paced DCU
batches (176 events of 2 cameras through 8 stages, as ``simnode`` makes them) as the wire carries them,
each decoded and checked, then merged into a run's open frames (:mod:`dcuscope.model.compiled`, called
from Python once per batch as the relay calls it); and, apart, the delay model's judgement per frame.
``bench_relay.py`` prints it beside the relay's figure: the relay's µs per event less this is what
Python, the sockets, the store and the pushes cost.

    .venv/bin/python benchmarks/floor.py [--quick]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from dcuscope.model import compiled  # noqa: E402
from dcuscope.model.delays import frame_delays  # noqa: E402
from dcuscope.model.frametable import frame_table  # noqa: E402
from dcuscope.probes.ship.simnode import header_for, synth_events  # noqa: E402
from dcuscope.protocol.events import EVENT_DTYPE  # noqa: E402
from dcuscope.protocol.wire import HEADER_SIZE, encode_batch  # noqa: E402
from dcuscope.relay.live.opentable import OpenTable  # noqa: E402

BATCH = 176


def compiled_floor(frames: int = 6000) -> dict | None:
    """µs per event of decoding, checking and merging paced batches, and µs per frame of judging them;
    None where the compiled core is unavailable."""
    core = compiled.load()
    if core is None:
        return None
    header = header_for("n", 2)
    stages = len(header.stages)
    events = synth_events(frames, 2, 30.0, 1_700_000_000_000_000_000, seed=1)
    batches = [encode_batch("ab" * 16, k, events[at:at + BATCH]) for k, at in enumerate(range(0, len(events), BATCH))]
    ids, marks, has_exit = np.array([0, 1], np.int64), np.full(2, -1, np.int64), np.zeros(stages, bool)
    table = OpenTable(stages, core)
    start = time.process_time()
    for data in batches:
        code, _, _ = core.decode_header(data, stages)
        assert code == compiled.BATCH_OK
        table.merge(np.frombuffer(data, EVENT_DTYPE, offset=HEADER_SIZE), ids, marks, has_exit, 0)
        if table.n > 4096:  # frames leave the table as the relay finalises them
            table.keep(np.arange(table.n) >= table.n - 512)
    merge_us = (time.process_time() - start) * 1e6 / len(events)
    whole = frame_table(header, events)
    start, rounds = time.process_time(), 0
    while rounds < 3 or time.process_time() - start < 0.5:
        frame_delays(whole)
        rounds += 1
    judge_us = (time.process_time() - start) * 1e6 / (rounds * len(whole))
    return {"decode_merge_us_per_event": round(merge_us, 3), "judge_us_per_frame": round(judge_us, 3)}


def describe(floor: dict | None) -> str:
    if floor is None:
        return f"compiled floor: n/a (the compiled core is unavailable: {compiled.unavailable_reason()})"
    return (f"compiled floor (this process, one call per batch): decode + check + merge "
            f"{floor['decode_merge_us_per_event']:.3f} µs/event; the delay model's judgement "
            f"{floor['judge_us_per_frame']:.3f} µs/frame")


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="a smoke test: 600 frames, not 6,000")
    args = p.parse_args()
    floor = compiled_floor(600 if args.quick else 6000)
    print(describe(floor))
    sys.exit(0 if floor is not None else 2)
