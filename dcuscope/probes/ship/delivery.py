"""What a node's run delivered to the relays: events stored (acknowledged), events not, relays
tried; the line every node command ends with, and the exit status it gives when a relay did not
acknowledge every event (``dcuscope run``, ``trace``, ``ship`` and the simulated node alike)."""

from __future__ import annotations

from dataclasses import dataclass, field

UNACKNOWLEDGED_STATUS = 3
"""Exit status of a node command whose probe events were not all acknowledged by a relay (none
reachable within ``--close-timeout``, the token refused, the node's buffer overflowed): distinct
from 1 (the pipeline failed) and 2 (bad configuration or arguments)."""


@dataclass
class Delivery:
    """One node's delivery to its relays, over one or more relay runs."""

    events: int = 0
    """Events handed to the relay exporter (including any it had to shed: its buffer full)."""
    stored: int = 0
    """Events a relay acknowledged: stored there."""
    tried: list[str] = field(default_factory=list)
    """The relays this node tried to reach, in the order it first tried them."""
    last_error: str = ""
    refused: str | None = None
    """Why a relay refused this node (its token), if one did."""
    spooled: int = 0
    """Events not acknowledged but kept in the spool: a later drain sends them (not lost)."""
    spool_dir: str = ""

    @property
    def unacknowledged(self) -> int:
        """Events neither stored nor kept in the spool: lost."""
        return self.events - self.stored - self.spooled

    @property
    def complete(self) -> bool:
        return self.unacknowledged == 0 and self.refused is None

    def __add__(self, other: Delivery) -> Delivery:
        return Delivery(self.events + other.events, self.stored + other.stored,
                        self.tried + [u for u in other.tried if u not in self.tried],
                        other.last_error or self.last_error, self.refused or other.refused,
                        self.spooled + other.spooled, other.spool_dir or self.spool_dir)

    def line(self) -> str:
        """'relay: 480 events stored (acknowledged), 0 not acknowledged; relays tried: URL'."""
        tried = ", ".join(self.tried) if self.tried else "none (no event to send)"
        text = (f"relay: {self.stored} events stored (acknowledged), {self.unacknowledged} not acknowledged; "
                f"relays tried: {tried}")
        if self.spooled:
            text += (f"; {self.spooled} events kept in the spool ({self.spool_dir}): they will be sent when a "
                     "relay stores again (dcuscope ship --drain, or the next run)")
        if (not self.complete or self.spooled) and (self.refused or self.last_error):
            text += f"; last error: {self.refused or self.last_error}"
        return text
