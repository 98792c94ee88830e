"""What Python 3.11 added that dcuscope uses, for Python 3.10 (Ubuntu 22.04: JetPack 6, DeepStream 7.1).

- :func:`timeout`: ``asyncio.timeout`` where there is one, else :class:`Deadline`, which cancels the
  task at the deadline and raises ``TimeoutError`` in its place, as 3.11's does.
- :data:`ASYNC_TIMEOUTS`: what an asyncio timeout raises on every version. Before 3.11
  ``asyncio.TimeoutError`` (``wait_for``'s, aiohttp's) is not the built-in ``TimeoutError``; catch both.
- :data:`NEW_PROCESS_GROUP`: ``subprocess.Popen`` keywords that start the child in a process group of
  its own (``process_group=0`` from 3.11, ``os.setpgrp`` in the child before).
- ``tomllib``: the ``tomli`` backport below 3.11 (a conditional dependency, pyproject.toml).

``tests/test_portability.py`` checks with vermin that nothing newer than 3.10 is used elsewhere.
"""

from __future__ import annotations

import asyncio
import os
import sys

ASYNC_TIMEOUTS = (TimeoutError, asyncio.TimeoutError)


class Deadline:
    """``async with Deadline(seconds)`` (None: none), as Python 3.11's ``asyncio.timeout``: the task is
    cancelled at the deadline and ``TimeoutError`` raised in its place; a cancellation from elsewhere
    goes through as it is."""

    def __init__(self, delay: float | None) -> None:
        self._delay, self._handle, self._expired = delay, None, False

    async def __aenter__(self) -> Deadline:
        if self._delay is not None:
            task = asyncio.current_task()
            self._handle = asyncio.get_running_loop().call_later(max(self._delay, 0), self._expire, task)
        return self

    def _expire(self, task: asyncio.Task) -> None:
        self._expired = True
        task.cancel()

    async def __aexit__(self, kind, exc, tb) -> None:
        if self._handle is not None:
            self._handle.cancel()
        if self._expired and kind is asyncio.CancelledError:
            raise TimeoutError from exc


if sys.version_info >= (3, 11):
    import tomllib  # noqa: F401 (re-exported)

    timeout = asyncio.timeout  # novermin
    NEW_PROCESS_GROUP: dict = {"process_group": 0}
else:  # Python 3.10
    import tomli as tomllib  # noqa: F401 (re-exported)

    timeout = Deadline
    NEW_PROCESS_GROUP = {"preexec_fn": os.setpgrp}
