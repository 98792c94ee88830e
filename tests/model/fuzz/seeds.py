"""Seed inputs of the fuzz harness (fuzz_core.c): real batches as the wire carries them, each after a
stage count and a link graph. ``python -m tests.model.fuzz.seeds FOLDER`` writes synthetic ones."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.wire import encode_batch

RUN = "ab" * 16


def seed(events: np.ndarray, stages: int, links: list, seq: int, compress: bool = False) -> bytes:
    links = [(a, b) for a, b in links if 0 <= a < 128 and 0 <= b < 128][:7]
    head = bytes([stages - 1, len(links)]) + bytes(v for pair in links for v in pair)
    return head + encode_batch(RUN, seq, events, compress)


def write(folder: Path, traces: dict | None = None) -> list[Path]:
    """Seeds from synthetic runs (drops, several sources) and from ``traces`` (name -> Trace) of at most 12
    stages, in batches of 150 events; returns their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    made = []
    header = header_for("n", 2)
    runs = [(synth_events(60, 2, 30.0, 1_700_000_000_000_000_000, drop_rate=0.2, seed=3), len(header.stages), [])]
    for trace in (traces or {}).values():
        if len(trace.header.stages) <= 12:
            runs.append((trace.events, len(trace.header.stages), [list(link) for link in trace.header.links]))
    for r, (events, stages, links) in enumerate(runs):
        for k, at in enumerate(range(0, min(len(events), 1500), 150)):
            path = folder / f"seed-{r}-{k}"
            path.write_bytes(seed(events[at:at + 150], stages, links, k, compress=k == 1))
            made.append(path)
    return made


if __name__ == "__main__":
    print(len(write(Path(sys.argv[1]))), "seeds written")
