"""What the relay knows about every run it has seen since it started: live pairing, clock, counters.

Shared by the ingest endpoint (which feeds it), the HTTP API and the UI namespace (which
read it). Everything runs on the relay's event loop; only storage works in its own thread.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from dcuscope.core.clocks import NEVER
from dcuscope.model.delays import FrameDelays, Series
from dcuscope.model.journeys import Joined
from dcuscope.protocol.errors import ProtocolError
from dcuscope.protocol.events import TraceHeader
from dcuscope.protocol.wire import Hello
from dcuscope.relay.clock.correction import Correction, correction_of
from dcuscope.relay.clock.entry import clock_entry
from dcuscope.relay.clock.model import ClockEstimator, segment_fault
from dcuscope.relay.errors import RelayError
from dcuscope.relay.guard.limits import MIB, Limits
from dcuscope.relay.live.framelimits import FrameLimits
from dcuscope.relay.live.journeys import LiveJourneys, parts_of
from dcuscope.relay.live.run import LiveConfig, LiveRun
from dcuscope.relay.live.runview import RunView, columns_block, frames_block, window_end_ns
from dcuscope.relay.live.seqset import SeqSet
from dcuscope.relay.store import base as db
from dcuscope.relay.store.runs import run_events
from dcuscope.relay.store.writer import Storage

RELOAD_SLICE = 262_144
STATS_MAX_AGE_S = 0.5
"""Whole-run statistics are recomputed at most this often per run (percentiles over every frame)."""
STATS_SHARE = 0.02
"""Share of the relay's time all runs' whole-run statistics may take when nobody asks for them fresh."""
WINDOW_MAX_AGE_S = 0.5
"""The rolling window's, unless asked fresh (the HTTP API), at most this often: shorter than the UI's
once-a-second pushes, so each push gets a new one, and a scrape at about the same time shares it."""
WINDOW_SHARE = 0.02
"""Share of the relay's time all runs' rolling windows may take when nobody asks for them fresh."""

OWNED_RETRY_MS = 500
"""How long a node whose run another relay owns waits before its next hello (that relay lets
it go once its connection to the node is seen dead, or dies, which releases it at once)."""

FrameObserver = Callable[["RunState", FrameDelays, Series], None]
"""Told of every finalised batch of a run's frames (see ``LiveRun.on_finalise``); it must be quick."""

log = logging.getLogger(__name__)


@dataclass
class WholeRunStats:
    """A run's whole-run statistics, recomputed only when new events came and, unless asked
    ``fresh``, at most every max(STATS_MAX_AGE_S, their last cost x runs / STATS_SHARE): all runs'
    together within STATS_SHARE of the relay's time, however many runs and however long (their
    percentiles are over every frame of the run, so they cost more as it goes on)."""

    stats: dict | None = None
    events: int = -1
    """``LiveRun.events`` when they were computed."""
    at: float = NEVER
    cost: float = 0.0

    def get(self, live: LiveRun, dropped: int, fresh: bool, runs: int = 1) -> dict:
        """``runs``: how many runs' statistics are kept up to date this way (their share is split)."""
        now = time.monotonic()
        due = fresh or now - self.at >= max(STATS_MAX_AGE_S, self.cost * runs / STATS_SHARE)
        if self.stats is None or (self.events != live.events and due):
            self.stats = live.run_stats(dropped)
            self.events, self.at, self.cost = live.events, now, time.monotonic() - now
        return self.stats


@dataclass
class WindowStats:
    """A run's rolling-window statistics, shared by the UI's pushes, the overview's rows and ``/metrics``.

    The window ends at the present on the node's clock (:func:`dcuscope.relay.live.runview.window_end_ns`),
    so it changes as new events come and as its frames age out. Once it holds nothing (a run that
    ended or went silent ``window_s`` ago) it stays as it is until new events come; it is
    recomputed at once when it comes to hold nothing. Otherwise it is recomputed, unless asked
    ``fresh`` (the HTTP API, which stores what it computed), at most every WINDOW_MAX_AGE_S, and
    no more often than keeps all runs' windows within WINDOW_SHARE of the relay's time: a window
    over many frames (a node far above the paper's rate) then refreshes less often instead of
    slowing the ingest."""

    stats: dict | None = None
    events: int = -1
    """``LiveRun.events`` when they were computed."""
    at: float = NEVER
    cost: float = 0.0

    def settled(self, live: LiveRun) -> bool:
        """Whether the statistics held stay as they are until ``live`` gets new events: nothing is left
        in the window to age out."""
        return (self.stats is not None and self.events == live.events
                and not self.stats["frames"]["complete"] and not self.stats["frames"]["incomplete"])

    def get(self, live: LiveRun, correction: Correction, fresh: bool, runs: int = 1,
            max_age_s: float = WINDOW_MAX_AGE_S) -> dict:
        """``runs``: how many runs' windows are kept up to date this way (their share is split);
        ``max_age_s``: how old the statistics held may be for this caller (the fleet's rows, rebuilt
        once a second, take one up to a second old: the one a page's statistics push made)."""
        now = time.monotonic()
        if self.settled(live):
            return self.stats
        end = window_end_ns(live, correction)
        # Every event of the run is older than the window now: it is empty, and cheap to say so
        # (whatever the last one cost), so a silent run reads 0 within window_s on a busy relay too.
        emptied = self.events == live.events and end - int(live.config.window_s * 1e9) > live.newest
        if (fresh or emptied or self.stats is None
                or now - self.at >= max(max_age_s, self.cost * runs / WINDOW_SHARE)):
            self.stats, self.events = live.window_stats(end), live.events
            self.at, self.cost = now, time.monotonic() - now
        return self.stats


@dataclass
class RunState:
    run: str
    node: str
    session: int
    header: TraceHeader
    live: LiveRun
    seqs: SeqSet
    """Batches stored."""
    storing: dict[int, asyncio.Future] = field(default_factory=dict)
    """Batches being stored: seq -> future of "stored"."""
    clock: ClockEstimator = field(default_factory=ClockEstimator)
    clock_rejected: int = 0
    """Clock samples refused (not from this relay's sync replies, or offset/round trip out of bounds)."""
    clock_forged: int = 0
    """UDP clock answers its node refused for a wrong tag, as it last reported."""
    clock_fault: str = ""
    """Why the last one was refused."""
    unsaved: dict = field(default_factory=dict)
    """Run fields (clock, end) storage failed to write: written again once it works."""
    ptp: dict = field(default_factory=lambda: {"state": "unavailable"})
    past: bool = False
    """Drained from the node's spool (hello ``spooled``): a past run, stored as itself, never live."""
    spool: dict | None = None
    """The node's spool as it last said: {bytes, oldest_ns} (protocol.wire.sanitize_spool)."""
    sid: str | None = None
    ended: bool = False
    written: int | None = None
    dropped: int = 0
    lost: int = 0
    duplicates: int = 0
    first_seen: float = field(default_factory=time.time)
    last_seen: float = field(default_factory=time.time)
    pushed: int = 0
    """Cursor of the newest frame pushed to the UI."""
    whole: WholeRunStats = field(default_factory=WholeRunStats)
    window: WindowStats = field(default_factory=WindowStats)
    secret_hash: str | None = None
    """Hash of the resume secret issued at the run's first hello."""
    conflicts: int = 0
    """Hellos of other runs refused because this run held the node's name."""
    conflict_at: float | None = None
    corrected_by: tuple | None = field(default=None, repr=False, compare=False)
    """(clock mode, ``clock``, ``clock.version``, ``ptp``, the Correction they give): :meth:`RelayState.correction`'s."""


@dataclass(frozen=True)
class Attached:
    run: RunState
    previous: str | None
    """This run's former connection, still open (the node reconnected before it was seen to go)."""
    displaced: str | None
    """The connection of the node's former run, silent for Limits.silent_s, that this run takes over from."""
    secret: str | None
    """The resume secret to hand the node (its first hello only)."""


class TryLater(RelayError):
    """A hello this relay cannot take now, though another try may succeed (here after
    ``retry_ms``, or on another relay): its run is owned by another relay, or the store fails."""

    def __init__(self, message: str, retry_ms: int) -> None:
        super().__init__(message)
        self.retry_ms = retry_ms


class RelayState:
    def __init__(self, storage: Storage, clock_mode: str, live_config: LiveConfig = LiveConfig(),
                 limits: Limits = Limits(), frame_limits: FrameLimits = FrameLimits()) -> None:
        self.storage = storage
        self.frame_limits = frame_limits
        self.clock_mode = clock_mode
        self.live_config = live_config
        self.limits = limits
        self.released = 0
        """Runs whose live state left memory (ended, superseded, refused or beyond runs_held)."""
        self.refused: dict[str, int] = {"name_taken": 0, "runs_held": 0, "resume_secret": 0, "sources": 0,
                                        "stages": 0, "name_chars": 0, "owned_elsewhere": 0}
        """Hellos and batches refused, per reason: a name or run taken, or a limit exceeded (the
        ingest counts those it finds)."""
        self.runs: dict[str, RunState] = {}
        self.nodes: dict[str, str] = {}
        """Node name -> its newest run."""
        self.started = time.time()
        self.relay_name = ""
        """How other relays and the pages name this one (``--name``; the server sets it once listening)."""
        self.observers: list[FrameObserver] = []
        """The exporters, told of every run's finalised frames (:meth:`observe`)."""
        self.fresh: set[str] = set()
        """Runs given events since the UI's pusher last looked (:meth:`note_events`)."""
        self.on_events: Callable[[], None] | None = None
        """Called when a run is given events (the pusher's wake-up)."""
        self.journeys = LiveJourneys()
        """The runs' crossings, joined across them when asked (:meth:`joined`)."""
        self._attach_lock = asyncio.Lock()

    def note_events(self, rs: RunState) -> None:
        """``rs`` was given events (the ingest calls this after adding a batch)."""
        self.fresh.add(rs.run)
        if self.on_events is not None:
            self.on_events()

    def holds(self, rs: RunState) -> bool:
        """Whether this relay holds ``rs``: on a shared store, while its node is connected here (a
        detached run kept to be shown may be taken by another relay at any time) and once its node
        said its end here (nobody takes it then: it is listed here until released, ``Limits.ended_keep_s``,
        though it ended before this relay wrote its row, where another relay's row of it goes stale);
        alone on its store, every run it keeps."""
        return not self.storage.shared or rs.sid is not None or rs.ended

    def live_session(self) -> int | None:
        for rs in self.runs.values():
            if rs.sid is not None and not rs.ended and not rs.past:
                return rs.session
        return None

    async def attach(self, hello: Hello, sid: str) -> Attached:
        """Bind a run to connection ``sid``; ProtocolError when the hello may not have it.

        Only whoever created a run may resume it (the secret issued at its first hello). A new
        run whose node name is held by a live run (connected, not ended, heard from within
        Limits.silent_s) is refused and counted as a conflict of the live one: it never replaces it.
        """
        async with self._attach_lock:
            rs = self.runs.get(hello.run)
            if rs is not None and rs.sid is None and self.storage.shared:
                # Another relay may have owned it meanwhile and stored more: read it again.
                self.release(rs.run)
                rs = None
            displaced = None
            issued = None
            if rs is not None:
                try:
                    db.check_resume(hello.run, rs.node, rs.header.stages, rs.secret_hash, hello.header.node,
                                    hello.header.stages, hello.secret)
                except RelayError as exc:
                    if isinstance(exc, db.ResumeRefused):
                        self.refused["resume_secret"] += 1
                    raise ProtocolError(str(exc)) from None
            else:
                holder = self.node_run(hello.header.node)
                if (holder is not None and self._holds_name(holder) and not hello.spooled
                        and not await self._resumes(hello)):
                    holder.conflicts += 1
                    holder.conflict_at = time.time()
                    self.refused["name_taken"] += 1
                    raise ProtocolError(f"node {holder.node!r} is streaming run {holder.run}: a second live "
                                        "run under the same name is refused")
                self._make_room()
                rs, issued = await self._take(hello)
                self.runs[hello.run] = rs
                if (holder is not None and holder.sid is not None and not holder.ended and not hello.spooled
                        and rs.first_seen >= holder.first_seen):
                    displaced = holder.sid
            if not hello.spooled:  # a drained past run is stored, never shown as the node's live one
                self._make_current(rs)
            self.rebalance()
            previous, rs.sid = rs.sid, sid
            rs.lost = max(rs.lost, hello.lost)
            rs.ptp = hello.ptp
            if not hello.spooled:  # a drain's hello says nothing of the live run's spool
                rs.spool = hello.spool
            rs.last_seen = time.time()
            return Attached(rs, previous if previous != sid else None, displaced, issued)

    async def _take(self, hello: Hello) -> tuple[RunState, str | None]:
        """Own the run in the store (a shared store: no other relay may hold it) and load it."""
        try:
            if not await self.storage.call("own_run", hello.run):
                self.refused["owned_elsewhere"] += 1
                raise TryLater(f"run {hello.run} is owned by another relay", OWNED_RETRY_MS)
            try:
                return await self._load(hello)
            except BaseException:
                self._disown(hello.run)
                raise
        except db.StoreUnavailable as exc:
            raise TryLater(str(exc), self.storage.retry_ms()) from exc
        except TryLater:
            raise
        except RelayError as exc:
            if isinstance(exc, db.ResumeRefused):
                self.refused["resume_secret"] += 1
            raise ProtocolError(str(exc)) from exc

    def _disown(self, run: str) -> None:
        """Give the run's ownership back in the store (queued after its batches being stored)."""
        if self.storage.shared:
            task = asyncio.ensure_future(self.storage.call("disown_run", run))
            task.add_done_callback(_quietly)

    async def _resumes(self, hello: Hello) -> bool:
        """Whether ``hello`` claims a stored run (kept apart from its node's live run if it is
        resumed) rather than a new one; a secret presented for a run never stored claims nothing."""
        return hello.secret is not None and await self.storage.call("run_stored", hello.run)

    def _holds_name(self, rs: RunState) -> bool:
        # Longer than a short network stall (tests/relay/test_netcut.py holds one for 5 s).
        return rs.sid is not None and not rs.ended and time.time() - rs.last_seen < self.limits.silent_s

    def _make_current(self, rs: RunState) -> None:
        """The node's newest run is its current one; its former run leaves memory once detached."""
        current = self.nodes.get(rs.node)
        if current is None or current not in self.runs or self.runs[current].first_seen <= rs.first_seen:
            self.nodes[rs.node] = rs.run
            old = self.runs.get(current) if current != rs.run else None
            if old is not None and old.sid is None:
                self.release(old.run)

    def _make_room(self) -> None:
        """Release detached runs, least recently heard first, until a new one fits runs_held."""
        if len(self.runs) < self.limits.runs_held:
            return
        detached = sorted((rs for rs in self.runs.values() if rs.sid is None), key=lambda rs: rs.last_seen)
        for rs in detached[:len(self.runs) - self.limits.runs_held + 1]:
            self.release(rs.run)
        if len(self.runs) >= self.limits.runs_held:
            self.refused["runs_held"] += 1
            raise ProtocolError(f"the relay holds {len(self.runs)} connected runs, its limit "
                                "(--limit runs_held)")

    def release(self, run: str) -> None:
        """Drop a run's live state (it stays stored, and comes back from storage if resumed)."""
        rs = self.runs.pop(run, None)
        if rs is None:
            return
        # The exporters' callback refers to the run (see _load): a cycle rs -> live -> callback -> rs
        # that would keep the run's arrays (up to run_mb) until a full garbage collection, one per
        # restart of a node piling up meanwhile. Without it the run's memory goes as it leaves.
        rs.live.on_finalise = None
        self.journeys.forget(run)
        self.released += 1
        if self.nodes.get(rs.node) == run:
            del self.nodes[rs.node]
        self._disown(run)
        self.rebalance()

    def release_ended(self, now: float | None = None) -> list[str]:
        """Release the runs that ended, their node gone, longer than ``Limits.ended_keep_s`` ago: the fleet's
        live rows are for what runs (three ended runs beside two live ones would make five rows, more than a
        page opens by itself). They stay stored. Returns the nodes whose run left."""
        now = time.time() if now is None else now
        keep = self.limits.ended_keep_s
        gone = [rs for rs in self.runs.values() if rs.ended and rs.sid is None and now - rs.last_seen >= keep]
        for rs in gone:
            self.release(rs.run)
        return [rs.node for rs in gone]

    async def reject(self, run: str, reason: str) -> None:
        """A run the relay closed for what it sent: kept apart from sessions, out of memory."""
        self.release(run)
        try:
            await self.storage.call("mark_rejected", run, reason)
        except RelayError:  # storage failing is reported where it fails; the run is out of memory
            pass

    async def _load(self, hello: Hello) -> tuple[RunState, str | None]:
        header = hello.header
        past = (header.started_ns or None) if hello.spooled else None
        stored_header = dict(header.to_dict(), spooled=True) if hello.spooled else header.to_dict()
        session, first_seen_ns, issued = await self.storage.call("register_run", hello.run, header.node,
                                                                 stored_header, self.live_session(), hello.secret,
                                                                 past)
        seqs = SeqSet(await self.storage.call("stored_seqs", hello.run))
        live = LiveRun(header, self.live_config, self.run_budget(len(self.runs) + 1))
        if seqs:
            # The relay restarted while this run went on: rebuild its live state from storage,
            # in slices, so that only the frames of one slice are ever open at once.
            events = await self.storage.call(run_events, hello.run)
            self.journeys.forget(hello.run)
            self.journeys.add(hello.run, events)
            for i in range(0, len(events), RELOAD_SLICE):
                live.add(events[i:i + RELOAD_SLICE])
                live.maintain()
                await asyncio.sleep(0)  # the other connections are served meanwhile (their pings too)
        secret_hash = db.secret_hash(issued if issued is not None else hello.secret)
        # A resumed run goes on with its stored clock history (the next write keeps exactly what is held).
        history = [s for s in await self.storage.call("run_history", hello.run) if segment_fault(s) is None]
        rs = RunState(run=hello.run, node=header.node, session=session, header=header, live=live, seqs=seqs,
                      first_seen=first_seen_ns / 1e9, secret_hash=secret_hash, clock=ClockEstimator(history=history),
                      past=hello.spooled)
        # Frames rebuilt from storage above were exported before the relay restarted: not again.
        live.on_finalise = lambda fd, values: self._finalised(rs, fd, values)
        return rs, issued

    def _finalised(self, rs: RunState, fd: FrameDelays, values: Series) -> None:
        for observer in self.observers:
            try:
                observer(rs, fd, values)
            except Exception:  # noqa: BLE001 - an exporter's fault must not stop the ingest
                log.exception("exporter %s failed on %d frames of %s", getattr(observer, "__qualname__", observer),
                              len(fd), rs.node)

    # --- memory -------------------------------------------------------------------------------

    def run_budget(self, runs: int) -> int:
        """Bytes each run's live state may hold when ``runs`` runs hold one: an equal share of
        ``live_mb``, at most ``run_mb``."""
        return int(min(self.limits.run_mb, self.limits.live_mb / max(1, runs)) * MIB)

    def rebalance(self) -> None:
        """Give every run its share again (call whenever runs join or leave memory)."""
        budget = self.run_budget(len(self.runs))
        for rs in self.runs.values():
            rs.live.set_budget(budget)

    def memory_view(self) -> dict:
        """What the live states hold, for /api/health."""
        return {"live_bytes": sum(rs.live.nbytes for rs in self.runs.values()),
                "live_budget_bytes": int(self.limits.live_mb * MIB), "run_budget_bytes": self.run_budget(len(self.runs)),
                "runs_with_live_state": len(self.runs)}

    def detach(self, run: str, sid: str) -> None:
        """Connection ``sid`` of ``run`` ended; a run that is not its node's current one leaves memory."""
        rs = self.runs.get(run)
        if rs is not None and rs.sid == sid:
            rs.sid = None
            rs.last_seen = time.time()
            if self.nodes.get(rs.node) != run:
                self.release(run)
            else:  # kept to be shown, but another relay may take it now
                self._disown(run)

    def node_run(self, node: str) -> RunState | None:
        run = self.nodes.get(node)
        return self.runs.get(run) if run else None

    # --- views ----------------------------------------------------------------------------------

    def correction(self, rs: RunState) -> Correction:
        """What is subtracted from ``rs``'s timestamps, per timestamp, and its bound. Made again only
        when a clock report or a PTP state came (a report replaces ``rs.ptp``): each push and
        statistic of a run asks for it, and a history of 256 estimates takes ~0.2 ms to make into one."""
        clock, made = rs.clock, rs.corrected_by
        if (made is None or made[0] != self.clock_mode or made[1] is not clock or made[2] != clock.version
                or made[3] is not rs.ptp):
            made = (self.clock_mode, clock, clock.version, rs.ptp,
                    correction_of(self.clock_mode, clock.estimate(), rs.ptp, history=clock.history))
            rs.corrected_by = made
        return made[4]

    def clock_view(self, rs: RunState) -> dict:
        est = rs.clock.estimate()
        correction = self.correction(rs)
        corr, bound = correction.at(time.time_ns() + (est.offset_ns if est is not None else 0))
        view = {"mode": self.clock_mode, "applied": correction.applied, "why": correction.why,
                "correction_ns": corr, "correction_us": corr / 1e3, "correction_uncertainty_ns": bound,
                "rejected": rs.clock_rejected, "forged": rs.clock_forged}
        if rs.clock_fault:
            view["rejected_why"] = rs.clock_fault
        if est is not None:
            view.update(offset_ns=est.offset_ns, offset_us=est.offset_ns / 1e3,
                        uncertainty_ns=est.uncertainty_ns, uncertainty_us=est.uncertainty_ns / 1e3,
                        rtt_us=est.rtt_ns / 1e3, samples=est.samples, points=est.points, drift_ppm=est.drift_ppb / 1e3,
                        drift_uncertainty_ppm=est.growth_ppb / 1e3, via=est.via)
        else:
            view.update(offset_ns=None, offset_us=None, uncertainty_ns=None, uncertainty_us=None, rtt_us=None,
                        samples=0, points=0, drift_ppm=None, drift_uncertainty_ppm=None, via=None)
        view.update(history=len(rs.clock.history), restarts=rs.clock.restarts)
        return view

    def node_view(self, rs: RunState) -> dict:
        live = rs.live
        limit = self.frame_limits.limit_ns(rs.node)
        return {
            "node": rs.node, "run": rs.run, "session": rs.session, "connected": rs.sid is not None,
            "ended": rs.ended, "stages": rs.header.stages, "kinds": rs.header.kinds, "sources": {str(k): v for k, v in rs.header.sources.items()},
            "links": rs.header.links, "lineage_unknown": rs.header.lineage_unknown,
            "clock": self.clock_view(rs), "ptp": rs.ptp,
            "events": live.events, "duplicates": rs.duplicates, "written": rs.written,
            "dropped": rs.dropped, "lost": rs.lost, "drops": rs.dropped + rs.lost,
            "conflicts": rs.conflicts, "conflict_at": rs.conflict_at,
            "frames": {"shown": live.visible, "finalised": live.finalised, "evicted": live.evicted,
                       "late_events": live.late},
            "last_seen": rs.last_seen, "frame_limit_ms": None if limit is None else limit / 1e6,
            **spool_view(rs.spool),
        }

    def nodes_view(self) -> list[dict]:
        return [self.node_view(self.runs[run]) for _, run in sorted(self.nodes.items())]

    def joined(self, fresh: bool = False) -> Joined:
        """Frames that went from one held run's pipeline to another's, joined on the relay's clock
        (:mod:`dcuscope.relay.live.journeys`)."""
        held = [rs for rs in self.runs.values() if self.holds(rs)]
        return self.journeys.joined(parts_of(held, self.correction, self.live_config.recent_frames), fresh)

    def stats(self, rs: RunState, fresh: bool = True) -> dict:
        """node_stats of the run (bottleneck included) + the rolling ``window`` + the ``clock`` entry
        (:mod:`dcuscope.relay.clock.entry`: the correction applied to its timestamps now, and its bound).

        Whole-run statistics take percentiles over every frame of the run, a cost that grows
        with it; unless ``fresh`` (the HTTP API), they are recomputed as :class:`WholeRunStats`
        allows, so that pushing every run's to browsers stays within ~2 % of the relay's time
        however long and however many the runs. The window, unless ``fresh``, as
        :class:`WindowStats` allows (which ``/metrics`` shares).
        """
        return dict(rs.whole.get(rs.live, rs.dropped, fresh, len(self.runs)), window=self.window(rs, fresh), node=rs.node,
                    run=rs.run, session=rs.session, lost=rs.lost, clock=clock_entry(self.correction(rs), time.time_ns()))

    def window(self, rs: RunState, fresh: bool = True, max_age_s: float = WINDOW_MAX_AGE_S) -> dict:
        """The run's rolling-window statistics, as :class:`WindowStats` allows unless ``fresh``."""
        return rs.window.get(rs.live, self.correction(rs), fresh, len(self.runs), max_age_s)

    def view(self, rs: RunState) -> RunView:
        """What the HTTP API and the pushes read of ``rs`` (:mod:`dcuscope.relay.live.runview`)."""
        return RunView(rs.node, rs.run, rs.session, rs.header, rs.live, self.correction(rs),
                       lambda fresh: self.stats(rs, fresh), self.relay_name)

    def frames_view(self, rs: RunState, since: int = 0, limit: int = 200, newest: bool = False) -> dict:
        """Complete frames after cursor ``since`` (:func:`dcuscope.relay.live.runview.frames_block`)."""
        return frames_block(self.view(rs), since, limit, newest)

    def frames_columns(self, rs: RunState, since: int, limit: int) -> tuple[dict, tuple]:
        """The newest ``limit`` complete frames after ``since`` as pushed (:func:`dcuscope.relay.live.runview.columns_block`)."""
        return columns_block(self.view(rs), since, limit)


def _quietly(task: asyncio.Future) -> None:
    # A failed disown needs no word: the store failing is logged where it fails, and a lost
    # connection released every lock it held.
    if not task.cancelled():
        task.exception()


def spool_view(spool: dict | None) -> dict:
    """``spool_bytes`` (None: the node keeps no spool) and ``spool_oldest_age_s`` (None: it holds nothing)."""
    if spool is None:
        return {"spool_bytes": None, "spool_oldest_age_s": None}
    oldest = spool.get("oldest_ns")
    return {"spool_bytes": spool["bytes"],
            "spool_oldest_age_s": None if oldest is None else max(0.0, time.time() - oldest / 1e9)}
