"""asyncio helpers of the node's side of the relay protocol."""

from __future__ import annotations

import asyncio

from dcuscope.core.pycompat import ASYNC_TIMEOUTS, timeout


async def wait_event(event: asyncio.Event, timeout_s: float | None) -> bool:
    """Wait for ``event`` at most ``timeout_s`` (None: for as long as it takes); True if it was
    set. (``asyncio.timeout`` costs no extra task per wait, unlike ``wait_for``: this runs up to
    hundreds of times a second.)"""
    try:
        async with timeout(timeout_s):
            await event.wait()
        return True
    except ASYNC_TIMEOUTS:
        return False


def seconds(ms: int | None) -> float | None:
    return ms / 1000 if ms is not None else None


def describe(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__
