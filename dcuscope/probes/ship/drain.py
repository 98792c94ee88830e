"""Draining a node's spool (:mod:`dcuscope.probes.ship.spool`): every spooled run is sent again as
itself (its run id, its resume secret, its header), so that the relay stores each batch once, in
the run's own session, at its own times; a run whose batches were all stored and whose end the
relay heard leaves the spool. ``dcuscope ship --drain`` does it in the foreground; the node
commands (``run``, ``trace``, ``ship`` with ``--relay``) start it in the background
(:func:`drain_in_background`), said in one line."""

from __future__ import annotations

import threading
import time
from typing import Callable

from dcuscope.probes.ship.delivery import Delivery
from dcuscope.probes.ship.nodetls import RelayTls
from dcuscope.probes.ship.relayexport import RelayExporter
from dcuscope.probes.ship.spool import Spool, SpooledRun
from dcuscope.probes.ship.spoolfile import SpoolError
from dcuscope.protocol.events import EXPORTER_CLOSE_S, TraceHeader


def drain(spool: Spool, relay: str | None, token: str | None, tls: RelayTls | None = None, *,
          close_timeout_s: float = EXPORTER_CLOSE_S, say: Callable[[str], None] = print,
          skip: frozenset[str] = frozenset()) -> Delivery:
    """Send every spooled run not being shipped (nor in ``skip``) to ``relay`` (None: the relays it
    was spooled for); a run goes on while the relay acknowledges, ``close_timeout_s`` at most
    without an acknowledgement."""
    total = Delivery()
    runs = [r for r in spool.runs() if r.run not in skip]
    for k, info in enumerate(runs):
        if info.in_use:
            say(f"drain: run {info.run} of {info.node} is being shipped by another process: skipped")
            continue
        delivery, reached = drain_run(spool, info, relay, token, tls, close_timeout_s=close_timeout_s, say=say)
        total += delivery
        if not reached and relay is not None:  # the same relay for every run: the others would wait as long
            say(f"drain: no relay of {relay} reached within {close_timeout_s:g} s; {len(runs) - k - 1} more run(s) "
                "stay in the spool")
            break
    return total


def drain_run(spool: Spool, info: SpooledRun, relay: str | None, token: str | None, tls: RelayTls | None, *,
              close_timeout_s: float, say: Callable[[str], None]) -> tuple[Delivery, bool]:
    """Send one spooled run; what it delivered, and whether a relay was reached."""
    try:
        run = spool.open_run(info.run)
    except SpoolError as exc:
        say(f"drain: run {info.run}: {exc}: skipped")
        return Delivery(), True
    if run is None:
        say(f"drain: run {info.run} of {info.node} is being shipped by another process: skipped")
        return Delivery(), True
    relays = relay or ",".join(run.meta.get("relays", []))
    if not relays:
        run.close(False)
        say(f"drain: run {info.run} of {info.node} names no relay: give --relay")
        return Delivery(), True
    header = TraceHeader.from_dict(run.meta["header"])
    events = run.events
    say(f"drain: run {info.run} of {info.node}: {events} events ({info.bytes} bytes) to {relays}")
    started = time.monotonic()
    exporter = RelayExporter(relays, run.meta["node"], token=token, clock=header.clock, tls=tls,
                             close_timeout_s=close_timeout_s, resume=run)
    exporter.start(header)
    exporter.close(0, progress=lambda stored, total: say(
        f"drain: run {info.run}: {stored} of {total} events stored "
        f"({stored / max(1e-9, time.monotonic() - started):.0f}/s)"))
    delivery = exporter.delivery()
    took = time.monotonic() - started
    if exporter.spool_gone:
        say(f"drain: run {info.run} of {info.node}: all {delivery.stored} events stored in {took:.1f} s "
            f"({delivery.stored / max(took, 1e-9):.0f}/s); its spool is deleted")
    else:
        say(f"drain: run {info.run} of {info.node}: {delivery.stored} of {events} events stored; "
            f"the rest stays in the spool ({exporter.relays.last_error or 'the run end not acknowledged'})")
    return delivery, exporter.counters()["connects"] > 0


def drain_in_background(spool: Spool, relay: str, token: str | None, tls: RelayTls | None,
                        say: Callable[[str], None], skip: frozenset[str] = frozenset()) -> threading.Thread | None:
    """Start draining the runs spooled earlier on this machine (a daemon thread), said in one
    line; None if there are none. A run being shipped (locked) is skipped: the caller's own, made
    after this, or one another process ships."""
    waiting = [r for r in spool.runs() if not r.in_use and r.run not in skip]
    if not waiting:
        return None
    events = sum(r.events for r in waiting)
    say(f"spool: sending {len(waiting)} earlier run(s), {events} events kept in {spool.path}, in the background")
    thread = threading.Thread(target=drain, args=(spool, relay, token, tls),
                              kwargs={"say": lambda line: None, "skip": skip}, name="dcuscope-drain", daemon=True)
    thread.start()
    return thread
