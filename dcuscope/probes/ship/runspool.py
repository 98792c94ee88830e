"""One run's spool (:mod:`dcuscope.probes.ship.spool`): its segments of batch records and its ``run.json``,
held by whoever ships the run. Batches are appended as they are cut, read back when their turn to be
sent comes (a memory bound let them go), and deleted by segment once a relay acknowledged every batch
in it; the folder goes once nothing is left and the relay heard the run's end."""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path
from typing import Protocol

from dcuscope.probes.ship.spoolfile import (FILE_MODE, META, RECORD, SEGMENT_HEAD, Record, SpoolError, encode_record,
                                            read_payload, segment_head, segment_name, write_json)

log = logging.getLogger(__name__)


class Folder(Protocol):
    """What a run's spool asks of its folder (:class:`dcuscope.probes.ship.spool.Spool`)."""
    fsync_s: float
    segment_bytes: int

    def make_room(self, own: RunSpool, need: int) -> list[tuple[int, int]]: ...
    def removed(self, size: int) -> None: ...
    def say_full(self) -> None: ...


class RunSpool:
    """One run's spool, held (its lock) by whoever ships the run."""

    def __init__(self, spool: Folder, folder: Path, meta: dict, lock_fd: int,
                 index: dict[int, tuple[Path, Record]], segments: list[Path]) -> None:
        self.spool, self.folder, self.meta = spool, folder, meta
        self._lock_fd: int | None = lock_fd
        self._where = index
        self._pending = {seg: 0 for seg in segments}
        self._seg_events = {seg: 0 for seg in segments}
        for seg, r in index.values():
            self._pending[seg] += 1
            self._seg_events[seg] += r.events
        self.events = sum(self._seg_events.values())
        """Events of the batches held (not acknowledged)."""
        self._died_end = self._end_from_records() if index and not isinstance(meta.get("end"), dict) else None
        """A run whose process died said no end: what its records say, counted when it was opened
        (before a drain's acknowledgements remove any)."""
        self._fd: int | None = None
        self._current: Path | None = None
        self._current_bytes = 0
        self._synced_at = time.monotonic()
        self._dirty = False
        self.torn_bytes = 0
        self.broken: str | None = None
        """Why appending stopped (a full disk, an I/O error): the run goes on in memory only."""

    @property
    def run(self) -> str:
        return self.folder.name

    def holds(self, seq: int) -> bool:
        return seq in self._where

    def next_seq(self) -> int:
        return max(self._where, default=-1) + 1

    def pending(self) -> list[tuple[int, int]]:
        """(seq, events) of every batch held, in order."""
        return sorted((seq, r.events) for seq, (_, r) in self._where.items())

    # --- writing --------------------------------------------------------------------------------

    def append(self, seq: int, events: int, payload: bytes) -> list[tuple[int, int]]:
        """Append batch ``seq``; the (seq, events) of this run's batches dropped to make room.
        SpoolError if it could not be written (the spool is then :attr:`broken`)."""
        if self.broken:
            raise SpoolError(self.broken)
        record = encode_record(seq, events, payload)
        try:
            dropped = self.spool.make_room(self, len(record) + (SEGMENT_HEAD.size if self._rolls() else 0))
            if self._rolls():
                self._roll(seq)
            offset = self._current_bytes + RECORD.size
            view = memoryview(record)
            while view:
                view = view[os.write(self._fd, view):]
        except OSError as exc:
            self.broken = f"the spool {self.folder} could not be written: {exc.strerror or exc}"
            raise SpoolError(self.broken) from None
        self._current_bytes += len(record)
        self._where[seq] = (self._current, Record(seq, events, offset, len(payload), RECORD.unpack_from(record)[1]))
        self._pending[self._current] += 1
        self._seg_events[self._current] += events
        self.events += events
        self._dirty = True
        if time.monotonic() - self._synced_at >= self.spool.fsync_s:
            self.sync()
        return dropped

    def _rolls(self) -> bool:
        return self._fd is None or self._current_bytes >= self.spool.segment_bytes

    def _roll(self, seq: int) -> None:
        if self._fd is not None:
            self.sync()
            os.close(self._fd)
            done = self._current
            self._fd = None
            if done is not None and not self._pending.get(done):
                self._remove(done, acked=True)
        path = self.folder / segment_name(seq)
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, FILE_MODE)
        os.write(self._fd, segment_head(time.time_ns()))
        self._current, self._current_bytes = path, SEGMENT_HEAD.size
        self._pending[path] = self._seg_events[path] = 0

    def sync(self) -> None:
        if self._fd is not None and self._dirty:
            try:
                os.fdatasync(self._fd)
            except OSError as exc:
                self.broken = f"the spool {self.folder} could not be synced: {exc.strerror or exc}"
                log.warning("spool: %s", self.broken)
            self._dirty = False
        self._synced_at = time.monotonic()

    # --- reading and acknowledging --------------------------------------------------------------

    def read(self, seq: int) -> bytes:
        """Batch ``seq`` as it was spooled (SpoolError if its record changed on disk)."""
        seg, record = self._where[seq]
        return read_payload(seg, record)

    def acked(self, seq: int) -> None:
        """A relay stored batch ``seq``: a segment left with none is deleted."""
        entry = self._where.pop(seq, None)
        if entry is None:
            return
        seg = entry[0]
        self.events -= entry[1].events
        self._pending[seg] -= 1
        if not self._pending[seg] and seg != self._current:
            self._remove(seg, acked=True)

    def drop_oldest(self, need: int) -> list[tuple[int, int]]:
        """Drop this run's oldest segments (not the one being written) until ``need`` bytes went."""
        dropped: list[tuple[int, int]] = []
        for seg in sorted(self._pending):
            if need <= 0 or seg == self._current:
                break
            need -= seg.stat().st_size if seg.exists() else 0
            gone = sorted((s, r.events) for s, (p, r) in self._where.items() if p == seg)
            for s, n in gone:
                del self._where[s]
                self.events -= n
            dropped += gone
            self._remove(seg)
        if dropped:
            self.add_lost(sum(n for _, n in dropped))
            self.spool.say_full()
        return dropped

    def _remove(self, seg: Path, acked: bool = False) -> None:
        """Delete segment ``seg``; ``acked``: every batch in it was stored (counted in ``run.json``,
        so that a drain after a crash knows how many events the run wrote)."""
        self._pending.pop(seg, None)
        events = self._seg_events.pop(seg, 0)
        if acked and events:
            self.meta["acked_events"] = int(self.meta.get("acked_events", 0)) + events
            self._save()
        try:
            size = seg.stat().st_size
            seg.unlink()
        except FileNotFoundError:
            return
        self.spool.removed(size)

    # --- the run's facts ------------------------------------------------------------------------

    def _save(self) -> None:
        try:
            write_json(self.folder / META, self.meta)
        except OSError as exc:
            if not self.broken:  # else said already: a drain then counts the run's end from its records
                log.warning("spool: run %s: %s could not be written: %s", self.run, META, exc.strerror or exc)

    def set_secret(self, secret: str) -> None:
        if self.meta.get("secret") != secret:
            self.meta["secret"] = secret
            self._save()

    def add_lost(self, events: int) -> None:
        self.meta["lost"] = int(self.meta.get("lost", 0)) + events
        self._save()

    def end(self) -> dict:
        """What ``end`` tells the relay of this run: as its process said when it ended, or, for a
        process that died, what the spool knows (its events: stored before, given up, and held;
        its end: its last segment's last write)."""
        lost = int(self.meta.get("lost", 0))
        end = self.meta.get("end")
        if isinstance(end, dict):
            return {**end, "lost": int(end.get("lost", 0)) + lost}
        return dict(self._died_end or self._end_from_records(), lost=lost)

    def _end_from_records(self) -> dict:
        last = max((s.stat().st_mtime_ns for s in self._pending if s.exists()), default=time.time_ns())
        lost = int(self.meta.get("lost", 0))
        return {"events": int(self.meta.get("acked_events", 0)) + lost + self.events, "dropped": 0, "lost": lost,
                "ended_ns": last}

    def set_end(self, end: dict) -> None:
        self.meta["end"] = end
        self._save()

    def close(self, end_heard: bool) -> bool:
        """Sync and let go; the run's folder is deleted if nothing is left to send (every batch
        acknowledged and, with ``end_heard``, the relay told the run ended). True if it was."""
        if self._fd is not None:
            self.sync()
            os.close(self._fd)
            self._fd = None
        gone = not self._where and end_heard
        if gone:
            shutil.rmtree(self.folder, ignore_errors=True)
        else:
            for seg, n in list(self._pending.items()):
                if not n:
                    self._remove(seg, acked=True)
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None
        return gone
