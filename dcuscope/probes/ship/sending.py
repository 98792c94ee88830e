"""Sending an outbox's batches on one link (:func:`send`), and noticing a relay gone silent.

Batches go in order, at most the outbox's window in flight, none while the relay asked to hold
them (its storage fails). A relay that, while the node waits for it (batches in flight, or a
request's reply), says nothing for ``HEARTBEAT_S`` is pinged; one that says nothing for
``SILENCE_S``, not even the pong, is left: it froze, or the network between is cut (a frozen
relay keeps its connections open, so only silence shows it). A send the socket holds back (a cut
path fills the kernel's buffer, and the WebSocket's after it) is watched for that silence too:
it would wait for TCP's own timeout, many minutes, otherwise.
"""

from __future__ import annotations

import asyncio
import time

from dcuscope.probes.ship.aio import wait_event
from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.outbox import Outbox
from dcuscope.probes.ship.relaylink import Link
from dcuscope.protocol.wire import HEARTBEAT_S, SILENCE_S

ACK_TIMEOUT_S = 30.0
SILENCE_CHECK_S = 0.25
"""How often the sender, waiting, looks whether the relay went silent."""


async def send(link: Link, box: Outbox, progress: asyncio.Event) -> None:
    """Send ``box``'s batches on ``link`` until it fails (raises) or the task is cancelled;
    ``progress`` is set by whoever adds batches or takes acknowledgements."""
    while True:
        check_silence(link, box)
        while box.may_send():
            if time.monotonic() < box.hold_until:  # the relay's storage fails: hold every batch
                await asyncio.sleep(box.hold_until - time.monotonic())
                continue
            item = box.take()
            if item is None:
                continue
            await send_watched(link, box, item[0])
            box.sent += item[1]
        progress.clear()
        if not await wait_event(progress, SILENCE_CHECK_S):
            since = expecting(link, box)
            if since is not None and link.silent_s(since) >= HEARTBEAT_S:
                await link.ping()
            oldest = min(box.inflight.values(), default=time.monotonic())
            if time.monotonic() - oldest > ACK_TIMEOUT_S:
                raise ExportError(f"no acknowledgement for {ACK_TIMEOUT_S:.0f} s") from None


async def send_watched(link: Link, box: Outbox, data: bytes) -> None:
    """Send one batch; raise if the relay goes silent while the socket holds the send back."""
    sending = asyncio.ensure_future(link.send_batch(data))
    try:
        while not (await asyncio.wait({sending}, timeout=SILENCE_CHECK_S))[0]:
            check_silence(link, box)
    finally:
        sending.cancel()
    sending.result()


def expecting(link: Link, box: Outbox) -> float | None:
    """Since when the node has been waiting for the relay (batches in flight, a request's
    reply), or None if it waits for nothing."""
    starts = ([box.waiting_since] if box.inflight else []) + ([link.asked_at] if link.asked_at else [])
    return min(starts, default=None)


def check_silence(link: Link, box: Outbox) -> None:
    """Raise if the relay, while the node waits for it, said nothing for SILENCE_S (not even a pong)."""
    since = expecting(link, box)
    if since is not None:
        silent = link.silent_s(since)
        if silent >= SILENCE_S:
            raise ExportError(f"relay silent for {silent:.1f} s with {len(box.inflight)} batches unacknowledged")
