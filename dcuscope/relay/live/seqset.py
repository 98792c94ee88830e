"""The batch sequence numbers a run has delivered, in memory that does not grow with the run.

A node numbers its batches 0, 1, 2, ... and resends the unacknowledged ones after a cut, so
what was seen is almost always "everything below N" plus a few above it: that is what this
keeps (``low`` and the set of the ones above it).
"""

from __future__ import annotations

from typing import Iterable


class SeqSet:
    def __init__(self, seqs: Iterable[int] = ()) -> None:
        self.low = 0
        """Every seq below this was seen."""
        self._above: set[int] = set()
        for seq in seqs:
            self.add(seq)

    def __contains__(self, seq: int) -> bool:
        return seq < self.low or seq in self._above

    def __len__(self) -> int:
        return self.low + len(self._above)

    def __bool__(self) -> bool:
        return len(self) > 0

    def add(self, seq: int) -> None:
        if seq < self.low:
            return
        self._above.add(seq)
        while self.low in self._above:
            self._above.discard(self.low)
            self.low += 1

    def advance(self, floor: int) -> None:
        """Count every seq below ``floor`` as seen: the node acknowledged or gave up all of them
        (a batch its full buffer evicted never comes, and would otherwise hold ``low`` below
        it for the rest of the run, every later seq kept one by one)."""
        if floor <= self.low:
            return
        self._above = {seq for seq in self._above if seq >= floor}
        self.low = floor
        while self.low in self._above:
            self._above.discard(self.low)
            self.low += 1

    @property
    def held(self) -> int:
        """Numbers held individually (the memory it takes)."""
        return len(self._above)
