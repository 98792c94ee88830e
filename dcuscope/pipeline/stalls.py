"""Stall watch: a live source that stops delivering frames without failing is reported, and so is its
return; so is one that ends (a live source has no end of its own: its stream server ended it).

A stalled camera or stream posts no error (rtspsrc waits, a V4L2 device just goes quiet), so the
runner looks at each source's frame count a few times a second. No probe on the streaming path:
the frame stamp at the end of every source already counts the frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable


@dataclass
class Stall:
    started: float
    """time.monotonic() of the last frame before the stall (or of the start, if none came)."""
    seconds: float | None = None
    """How long it lasted (so far, at the end of the run); None while it goes on."""
    resumed: bool = False


@dataclass
class StallWatch:
    say: Callable[[str], None]
    stalls: dict[int, list[Stall]] = field(default_factory=dict)
    ended: set[int] = field(default_factory=set)
    """Live sources whose end of stream has been said."""
    _seen: dict[int, tuple[int, float]] = field(default_factory=dict)

    def start(self, sources: Iterable, now: float) -> None:
        for source in sources:
            self._seen[source.index] = (source.frames, now)

    def update(self, sources: Iterable, now: float) -> None:
        """``sources``: those still in the run (a failed one is reported elsewhere)."""
        sources = list(sources)
        for source in sources:
            if not source.config.is_live:
                continue
            if source.ended:
                others = any(s is not source and not s.ended for s in sources)
                self._check_end(source, others)
            elif source.config.stall_timeout > 0:
                self._check_stall(source, now)

    def _check_end(self, source, others: bool) -> None:
        """A live source has no end of its own: one that ends (a stream server that ends its stream) is said once."""
        if source.index in self.ended:
            return
        self.ended.add(source.index)
        then = "; the other sources go on" if others else ""
        self.say(f"\nsource {source.index} ({source.config.description}) ended: end of stream after "
                 f"{source.frames} frames{then}")

    def _check_stall(self, source, now: float) -> None:
        cfg = source.config
        frames = source.frames
        seen_frames, seen_at = self._seen.get(source.index, (frames, now))
        current = self._current(source.index)
        if frames != seen_frames:
            self._seen[source.index] = (frames, now)
            if current is not None:
                current.seconds, current.resumed = now - current.started, True
                self.say(f"\nsource {source.index} ({cfg.description}) resumed after "
                         f"{current.seconds:.1f} s without frames")
        elif current is None and now - seen_at >= cfg.stall_timeout:
            self.stalls.setdefault(source.index, []).append(Stall(seen_at))
            what = f"no frame for {now - seen_at:.1f} s" if frames else f"no frame yet after {now - seen_at:.1f} s"
            self.say(f"\nsource {source.index} ({cfg.description}) stalled: {what}; the other sources go on")

    def finish(self, now: float) -> None:
        for index in self.stalls:
            current = self._current(index)
            if current is not None:
                current.seconds = now - current.started

    def _current(self, index: int) -> Stall | None:
        runs = self.stalls.get(index)
        return runs[-1] if runs and not runs[-1].resumed else None


def describe(stalls: list[Stall]) -> str:
    """'stalled 2 times, 9.4 s without frames in all (still stalled at the end)'."""
    total = sum(s.seconds or 0.0 for s in stalls)
    still = not stalls[-1].resumed
    times = "once" if len(stalls) == 1 else f"{len(stalls)} times"
    return f"stalled {times}, {total:.1f} s without frames in all" + (" (still stalled at the end)" if still else "")
