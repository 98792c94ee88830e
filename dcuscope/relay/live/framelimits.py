"""How long a frame may take on each node: ``dcuscope relay --frame-limit [NODE=]MS``.

A frame's delay (origin to the end of its chain, the delay model's ``frame``) over its node's
limit is what the shipped alert rule fires on (``dcuscope_frame_delay_limit_seconds`` in
``/metrics``) and what the OTLP exporter always sends, beside its 1-in-N sample. A bare ``MS``
sets every node's limit; ``NODE=MS`` one node's (it wins over the bare one). No limit: none is
exported and no frame counts as over.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from dcuscope.relay.errors import RelayError

NS_PER_MS = 1_000_000
MAX_LIMIT_MS = 3_600_000.0
"""An hour: a larger limit is a typo (a frame's delay is milliseconds to seconds)."""


@dataclass(frozen=True)
class FrameLimits:
    default_ns: int | None = None
    per_node_ns: dict[str, int] = field(default_factory=dict)

    def limit_ns(self, node: str) -> int | None:
        """The limit on ``node``'s frame delay, ns; None when it has none."""
        return self.per_node_ns.get(node, self.default_ns)

    @classmethod
    def parse(cls, specs: Iterable[str]) -> FrameLimits:
        """From ``--frame-limit`` values (``MS`` or ``NODE=MS``); RelayError names a bad one."""
        default, per_node = None, {}
        for spec in specs:
            node, sep, ms = spec.rpartition("=")
            if sep and not node:
                raise RelayError(f"--frame-limit {spec!r}: give MS or NODE=MS")
            try:
                value = float(ms)
            except ValueError:
                raise RelayError(f"--frame-limit {spec!r}: {ms!r} is not a number of milliseconds") from None
            if not (math.isfinite(value) and 0 < value <= MAX_LIMIT_MS):
                raise RelayError(f"--frame-limit {spec!r}: the limit must be over 0 and at most {MAX_LIMIT_MS:.0f} ms")
            if sep:
                per_node[node] = round(value * NS_PER_MS)
            else:
                default = round(value * NS_PER_MS)
        return cls(default, per_node)
