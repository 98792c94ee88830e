"""A node's spool: every batch a run cuts is on disk from its cut until a relay acknowledged it
(after its commit), so that a DCU offline for hours, or a process that ends, crashes or loses
power, loses nothing that reached the disk.

Layout: ``DIR/<run id>/`` (0700) holds ``run.json`` (0600: the run's header, node, relays, resume
secret, events given up, how it ended) and segments of batch records (:mod:`dcuscope.probes.ship.spoolfile`),
a new one every SEGMENT_BYTES. A segment whose batches were all acknowledged is deleted; a run
whose batches were all acknowledged and whose end the relay heard goes whole. Whoever ships a run
holds its ``lock`` (flock): the run's own process, or a drain (:mod:`dcuscope.probes.ship.drain`).

Bounded: beyond ``max_bytes`` for the whole folder, the oldest segments go first (of runs nobody
ships, then the run's own), their events counted lost (in their ``run.json``, told to the relay
with the run). Durability: a segment is synced (fdatasync) at most every ``fsync_s`` and when the
run closes; a process killed loses nothing written (the page cache survives it), a power loss at
most the last ``fsync_s`` (DEFAULT_FSYNC_S, chosen by benchmarks/bench_spool.py).
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from dcuscope.probes.ship.runspool import RunSpool
from dcuscope.probes.ship.spoolfile import (FILE_MODE, META, SEGMENT_HEAD, Record, SpoolError, count_records, made_ns,
                                            make_dir, read_json, scan, write_json)

SEGMENT_BYTES = 8 << 20
DEFAULT_MAX_BYTES = 10 << 30
"""10 GiB, or half the file system's free space if that is less (:func:`default_max_bytes`): about
a day of a paper-sized DCU (4,300 events/s, 24 bytes an event)."""
DEFAULT_FSYNC_S = 0.2
LOCK = "lock"
FACTS_S = 10.0
"""How often a node lists its spool again for the facts its clock reports carry (every 2 s)."""

log = logging.getLogger(__name__)


def default_dir() -> Path:
    """``$XDG_STATE_HOME/dcuscope/spool`` (``~/.local/state/dcuscope/spool`` without it)."""
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "dcuscope" / "spool"


def default_max_bytes(path: Path) -> int:
    try:
        free = shutil.disk_usage(path).free
    except OSError:
        return DEFAULT_MAX_BYTES
    return max(SEGMENT_BYTES * 2, min(DEFAULT_MAX_BYTES, free // 2))


@dataclass
class SpooledRun:
    """What ``dcuscope spool`` lists of one run."""
    run: str
    node: str
    relays: list[str]
    batches: int
    events: int
    bytes: int
    oldest_ns: int | None
    """When the segment of its oldest spooled batch was made."""
    lost: int
    ended: bool
    in_use: bool
    """Its process, or a drain, ships it now."""


def _lock(path: Path) -> int | None:
    """An exclusive flock on ``path`` (made if missing), or None if another process holds it."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, FILE_MODE)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def _segments(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.seg"))


def _events_of(path: Path) -> tuple[int, int]:
    """(batches, events) of a segment, from its record headers (a listing: no payload read)."""
    try:
        return count_records(path)
    except OSError:
        return 0, 0


class Spool:
    """The spool folder ``path``, bounded to ``max_bytes`` (None: :func:`default_max_bytes`)."""

    def __init__(self, path: Path, max_bytes: int | None = None, fsync_s: float = DEFAULT_FSYNC_S) -> None:
        self.path = Path(path)
        make_dir(self.path)
        self.max_bytes = int(max_bytes) if max_bytes is not None else default_max_bytes(self.path)
        self.fsync_s = fsync_s
        self.segment_bytes = max(64 << 10, min(SEGMENT_BYTES, self.max_bytes // 8))
        """A new segment this often: at most an eighth of the bound, so that the oldest go a little at a time."""
        self._facts: tuple[float, dict] | None = None
        self._said_full = False
        self._unreadable: set[Path] = set()
        self._total: int | None = None
        """Bytes of every segment as this process last counted them (read from disk again when
        they seem to reach ``max_bytes``: drains in other processes delete segments)."""

    def run_dirs(self) -> list[Path]:
        return sorted(p for p in self.path.iterdir() if p.is_dir() and (p / META).exists())

    def _oldest_first(self) -> list[Path]:
        """The run folders by when their runs began (``created_ns``; run.json is rewritten as a run goes,
        so its time says nothing of the run's age), unreadable ones last."""
        def began(d: Path) -> int:
            try:
                return int(read_json(d / META).get("created_ns", 0))
            except (SpoolError, TypeError, ValueError):
                return 1 << 62
        return sorted(self.run_dirs(), key=began)

    def bytes(self) -> int:
        return sum(s.stat().st_size for d in self.run_dirs() for s in _segments(d))

    def facts(self) -> dict:
        """What a node tells its relay of its spool: ``bytes`` held (every run), ``oldest_ns`` (when
        the segment of its oldest held batch was made; None: none held). Read again at most every
        FACTS_S (a listing costs a stat and a 16-byte read a segment)."""
        now = time.monotonic()
        if self._facts is None or now - self._facts[0] >= FACTS_S:
            size, oldest = 0, None
            for d in self.run_dirs():
                for seg in _segments(d):
                    try:
                        n = seg.stat().st_size
                    except FileNotFoundError:
                        continue
                    size += n
                    made = made_ns(seg) if n > SEGMENT_HEAD.size else None
                    if made is not None:
                        oldest = made if oldest is None else min(oldest, made)
            self._facts = (now, {"bytes": size, "oldest_ns": oldest})
        return self._facts[1]

    def runs(self) -> list[SpooledRun]:
        out = []
        for d in self.run_dirs():
            try:
                meta = read_json(d / META)
            except SpoolError as exc:
                if d not in self._unreadable:  # once, however often the spool is listed
                    self._unreadable.add(d)
                    log.warning("spool: %s: skipped (dcuscope spool drop %s deletes it)", exc, d.name)
                continue
            batches = events = size = 0
            oldest = None
            for seg in _segments(d):
                b, e = _events_of(seg)
                batches, events, size = batches + b, events + e, size + seg.stat().st_size
                made = made_ns(seg)
                if b and made is not None:
                    oldest = made if oldest is None else min(oldest, made)
            fd = _lock(d / LOCK)
            if fd is not None:
                os.close(fd)
            out.append(SpooledRun(d.name, str(meta.get("node", "?")), list(meta.get("relays", [])), batches, events,
                                  size, oldest, int(meta.get("lost", 0)), meta.get("end") is not None, fd is None))
        return sorted(out, key=lambda r: (r.oldest_ns or 0, r.run))

    def create_run(self, run: str, node: str, header: dict, relays: list[str]) -> RunSpool:
        folder = self.path / run
        try:
            folder.mkdir(mode=0o700)
            fd = _lock(folder / LOCK)
            assert fd is not None  # a folder just made
            meta = {"version": 1, "run": run, "node": node, "header": header, "relays": relays,
                    "created_ns": time.time_ns(), "secret": None, "lost": 0, "end": None}
            write_json(folder / META, meta)
        except OSError as exc:
            raise SpoolError(f"the spool folder {self.path} cannot be used: {exc.strerror or exc}") from None
        return RunSpool(self, folder, meta, fd, {}, [])

    def open_run(self, run: str) -> RunSpool | None:
        """Run ``run``'s spool to ship it (its torn tails cut), or None if another process ships it."""
        folder = self.path / run
        fd = _lock(folder / LOCK)
        if fd is None:
            return None
        try:
            meta = read_json(folder / META)
            index: dict[int, tuple[Path, Record]] = {}
            cut = 0
            segments = []
            for seg in _segments(folder):
                records, torn = scan(seg)
                cut += torn
                if not records:
                    seg.unlink()
                    continue
                segments.append(seg)
                for r in records:
                    index[r.seq] = (seg, r)
        except BaseException:
            os.close(fd)
            raise
        spool = RunSpool(self, folder, meta, fd, index, segments)
        spool.torn_bytes = cut
        if cut:
            log.warning("spool: run %s: a torn or corrupt tail of %d bytes cut (a crash while writing); "
                        "the %d batches before it kept", run, cut, len(index))
        return spool

    def drop(self, run: str) -> SpooledRun:
        """Delete spooled run ``run`` (SpoolError if it is unknown or being shipped)."""
        found = [r for r in self.runs() if r.run == run]
        if not found:
            raise SpoolError(f"no spooled run {run} in {self.path}")
        fd = _lock(self.path / run / LOCK)
        if fd is None:
            raise SpoolError(f"run {run} is being shipped now (by its process or a drain)")
        try:
            shutil.rmtree(self.path / run)
        finally:
            os.close(fd)
        return found[0]

    def removed(self, size: int) -> None:
        """A run of this process deleted a segment of ``size`` bytes."""
        if self._total is not None:
            self._total -= size

    def say_full(self) -> None:
        if not self._said_full:
            self._said_full = True
            log.warning("spool full (%d bytes, --spool-max): the oldest events are dropped to make room, counted "
                        "lost (in the run's end)", self.max_bytes)

    def make_room(self, own: RunSpool, need: int) -> list[tuple[int, int]]:
        """Drop the oldest segments until ``need`` more bytes fit: other runs' first (those nobody
        ships), then ``own``'s (never its segment being written). The (seq, events) of ``own``'s
        batches dropped."""
        if self._total is not None and self._total + need <= self.max_bytes:
            self._total += need
            return []
        total = self.bytes()
        self._total = total + need
        if total + need <= self.max_bytes:
            return []
        for d in self._oldest_first():
            if d == own.folder:
                continue
            while total + need > self.max_bytes:
                segs = _segments(d)
                if not segs:
                    break
                fd = _lock(d / LOCK)
                if fd is None:
                    break
                try:
                    _, events = _events_of(segs[0])
                    size = segs[0].stat().st_size
                    meta = read_json(d / META)
                    meta["lost"] = int(meta.get("lost", 0)) + events
                    write_json(d / META, meta)
                    segs[0].unlink()
                    total -= size
                    self.say_full()
                finally:
                    os.close(fd)
            if total + need <= self.max_bytes:
                self._total = total + need
                return []
        self._total = total + need
        return own.drop_oldest(total + need - self.max_bytes)
