"""Which DCUs some browser of the fleet shows: the relay builds and sends only their pushes.

A browser subscribes to the DCUs it shows (``subscribe``, :mod:`dcuscope.relay.api.ui`). Its own relay knows
that; the relay holding a DCU may be another one. With ``--redis`` each relay therefore keeps its
browsers' wishes in one Redis hash (``KEY``: a field per relay, holding the DCUs its browsers show,
the frames per push they ask for, and until when the entry holds) and reads everyone's every
``PERIOD_S``: a relay builds the frames and statistics of a DCU it holds only while some browser
somewhere shows it. An entry a relay stopped refreshing (it died) lapses after ``TTL_S``. With
Redis down, only this relay's own browsers count (nothing else reaches them then).
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from dataclasses import dataclass

from dcuscope.relay.api.fanout import TIMEOUT_S, FanoutHealth, redis_client

KEY = "dcuscope:watching"
PERIOD_S = 0.5
TTL_S = 5.0
ALL = "*"
"""A wish for every DCU (a browser subscribed with ``nodes: null``)."""
MAX_FRAMES = 500
"""The most frames per push a wish may ask for."""

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Wish:
    nodes: frozenset[str] | None
    """None: every DCU."""
    max_frames: int


class Interest:
    def __init__(self, wishes: dict[str, Wish], url: str | None = None, health: FanoutHealth | None = None,
                 me: str = "") -> None:
        """``wishes``: this relay's browsers' (sid -> Wish, kept by the UI namespace)."""
        self.wishes, self.health, self.me = wishes, health, me
        self.remote: dict[str, set[int]] = {}
        """DCU (or ALL) -> the frames per push other relays' browsers showing it ask for."""
        self._redis = None
        if url is not None:
            self._redis = redis_client(url, socket_connect_timeout=TIMEOUT_S, socket_timeout=TIMEOUT_S)

    def wanted(self) -> dict[str, set[int]]:
        """DCU (or ALL) -> the frames per push the browsers showing it ask for (each a room of its own)."""
        out = {node: set(limits) for node, limits in self.remote.items()}
        for node, limits in self._mine().items():
            out.setdefault(node, set()).update(limits)
        return out

    def _mine(self) -> dict[str, set[int]]:
        out: dict[str, set[int]] = {}
        for wish in list(self.wishes.values()):
            for node in (ALL,) if wish.nodes is None else wish.nodes:
                out.setdefault(node, set()).add(wish.max_frames)
        return out

    @staticmethod
    def limit(wanted: dict[str, set[int]], node: str) -> int:
        """The most frames per push anyone showing ``node`` asks for (0: nobody shows it)."""
        return max(wanted.get(node, set()) | wanted.get(ALL, set()), default=0)

    async def run(self) -> None:
        while True:
            try:
                await self.sync()
            except Exception as exc:  # noqa: BLE001 - Redis failing is FanoutHealth's to say
                self.remote = {}
                log.debug("interest: %s", exc)
            await asyncio.sleep(PERIOD_S)

    async def sync(self) -> None:
        """Publish this relay's wishes, read everyone else's."""
        if self._redis is None or self.health is None or not self.health.ok:
            self.remote = {}
            return
        mine = {node: sorted(limits) for node, limits in self._mine().items()}
        now = time.time()
        pipe = self._redis.pipeline(transaction=False)
        if mine:
            pipe.hset(KEY, self.me, json.dumps({"until": now + TTL_S, "nodes": mine}))
        else:
            pipe.hdel(KEY, self.me)
        pipe.pexpire(KEY, int(TTL_S * 4000))
        pipe.hgetall(KEY)
        *_, entries = await asyncio.wait_for(pipe.execute(), TIMEOUT_S * 2)
        remote: dict[str, set[int]] = {}
        lapsed = []
        for field, text in entries.items():
            field = field.decode(errors="replace")
            if field == self.me:
                continue
            try:
                entry = json.loads(text)
                until, nodes = float(entry["until"]), dict(entry["nodes"])
            except (ValueError, KeyError, TypeError):
                lapsed.append(field)
                continue
            if until < now:
                lapsed.append(field)
                continue
            for node, limits in nodes.items():
                if isinstance(node, str) and isinstance(limits, list):
                    remote.setdefault(node, set()).update(m for m in limits if isinstance(m, int) and 0 < m <= MAX_FRAMES)
        if lapsed:
            await self._redis.hdel(KEY, *lapsed)
        self.remote = remote

    async def close(self) -> None:
        if self._redis is not None:
            try:
                await self._redis.hdel(KEY, self.me)
            except Exception:  # noqa: BLE001 - Redis may be gone; the entry lapses by itself
                pass
            await self._redis.aclose()
