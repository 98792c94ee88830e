"""When the relay pairs its runs' events into frames: a run some browser shows as soon as it is given
events, every run now and then.

The UI's ticker (:class:`dcuscope.relay.api.ui.Ticker`) drives it and pushes what it pairs: its rounds
(:meth:`Pairing.run`) follow the events (:meth:`dcuscope.relay.live.state.RelayState.note_events` wakes
them), each taking the runs given events since the last (:meth:`Pairing.take`), and its housekeeping
pairs the others (:meth:`Pairing.idle`). Which DCUs are shown the caller says, as a function of a
node (the most frames per push anyone showing it asks for; 0: nobody), so this module knows
nothing of browsers. Nothing is paired for a push while this relay's leases may have lapsed
(:meth:`dcuscope.relay.store.writer.Storage.leases_fresh`): runs it may have lost are not pushed.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable

from dcuscope.core.clocks import NEVER
from dcuscope.relay.live.run import maintain_all
from dcuscope.relay.live.state import RelayState, RunState

DEFAULT_PUSH_HZ = 30.0
PUSH_SHARE = 0.5
"""The most of the relay's CPU the pushes take (pairing what browsers show, packing, sending)."""
PUSH_BACKOFF_S = 1.0
"""The longest a push waits for the share above."""
IDLE_PERIOD_S = 0.5
"""How often runs nobody shows are paired (their frames shown, settled ones finalised)."""

Shown = Callable[[str], "int | None"]
"""A node -> the most frames per push anyone showing it asks for (0 or None: nobody shows it)."""

log = logging.getLogger(__name__)


class Pairing:
    """Pairs the runs browsers show as their events come, at most ``push_hz`` rounds a second, and
    every run each ``IDLE_PERIOD_S``."""

    def __init__(self, state: RelayState, push_hz: float = DEFAULT_PUSH_HZ) -> None:
        self.state = state
        self.period = 1.0 / push_hz
        self._wake = asyncio.Event()
        state.on_events = self._wake.set
        self._idle_at = NEVER

    async def run(self, push: Callable[[], Awaitable[object]]) -> None:
        """Call ``push`` (which takes the runs to push, :meth:`take`) each time runs were given events
        or :meth:`idle` found frames someone shows; an exception of one is logged, not raised."""
        last, spent = NEVER, 0.0
        while True:
            await self._wake.wait()
            # At most push_hz pushes a second, and the pushes at most PUSH_SHARE of the relay's CPU:
            # after a push that took d of CPU, the next starts d / PUSH_SHARE after its start at the
            # earliest (at most PUSH_BACKOFF_S). What came meanwhile goes in the next one, so a busy
            # relay pairs and pushes in larger steps (each costs about the same whatever it holds)
            # instead of falling behind. CPU, not wall time: a slow browser or a starved thread is
            # no reason to push less.
            wait = last + max(self.period, min(spent / PUSH_SHARE, PUSH_BACKOFF_S)) - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            self._wake.clear()
            last, cpu = time.monotonic(), time.thread_time()
            try:
                if self.state.storage.leases_fresh():  # else runs it may have lost wait for the leases' renewal
                    await push()
            except Exception:  # noqa: BLE001 - the heartbeat must survive a bad push
                log.exception("relay push failed")
            spent = time.thread_time() - cpu

    def take(self, shown: Shown) -> list[tuple[RunState, int]]:
        """The runs given events since the last take that are their node's newest run and shown,
        each with ``shown(node)``, paired (one pass of the delay model per graph, not per DCU)."""
        state = self.state
        fresh, state.fresh = state.fresh, set()
        taken = []
        for run in fresh:
            rs = state.runs.get(run)
            if rs is not None and state.nodes.get(rs.node) == run and (limit := shown(rs.node)):
                taken.append((rs, limit))
        maintain_all(rs.live for rs, _ in taken)
        return taken

    def idle(self, shown: Shown) -> None:
        """Pair every run, once an ``IDLE_PERIOD_S`` however often it is called: a run shown with frames
        not pushed yet goes to the next round (:meth:`run`), another's count as pushed."""
        if not self.state.storage.leases_fresh():
            return  # as in run: nothing is paired for a push until the leases are renewed
        now = time.monotonic()
        if now - self._idle_at < IDLE_PERIOD_S:
            return
        self._idle_at = now
        runs = self.state.runs.values()
        maintain_all(rs.live for rs in runs)
        for rs in runs:
            if rs.live.visible > rs.pushed:
                if shown(rs.node):
                    self.state.fresh.add(rs.run)
                    self._wake.set()
                else:
                    rs.pushed = rs.live.visible
