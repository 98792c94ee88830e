"""A frame's journey across pipelines: the ``link``/``key`` events of several nodes joined.

A frame that leaves one pipeline (an RTP sender's udpsink, a shmsink) and enters another (a
depayloader, a shmsrc) is a new frame there, with an identity of its own. Both ends recorded
a ``link`` event (when it was sent / when it arrived) and a ``key`` event (what both can compute
from what crossed: :mod:`dcuscope.protocol.events`). Joining the keys gives:

- the **hop**, a stage of its own: ``net DCU-1 → DCU-2`` (or ``shm …``), from the push that sent
  the frame returning on the sender to its first packet (its buffer) arriving on the receiver,
  on the clocks the traces hold (a stored session's: each node's, moved to the relay's, with
  the bound of each correction: a hop's error is the sum of its two nodes');
- the **journey** of every frame at the end of a chain: from its first origin (the camera's
  capture time where the source gave one) to its last timestamp on the last node, and its
  parts, each node's share and each hop's, which add up to it.

Honest where it cannot know: an arriving frame whose key no traced sender sent within
:data:`JOIN_WINDOW_NS` is ``untraced`` (its sender was not traced, or the key is not one a
sender recorded); one that two sent frames could be (the same key twice in the window: the same
bytes sent twice over shm, an RTP timestamp that wrapped) is ``ambiguous``: neither is joined,
never a guess. A frame sent between the first and the last frame a receiver got from that
sender, that the receiver never got, is ``lost`` on that hop.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dcuscope.model.delays import NS_PER_MS, summarize
from dcuscope.model.names import unique_names
from dcuscope.protocol.events import (ARRIVED_KINDS, CAPTURE, ENTER, EXIT, KEY, LINK, LINK_TRANSPORT, ORIGIN,
                                      SENT_KINDS)

JOIN_WINDOW_NS = 30 * 10**9
"""How far apart a frame's sending and its arrival may be (either way, clocks being what they are)
for the two to be joined: a key seen again further apart is another frame (an RTP timestamp
wraps after about 13 hours at 90 kHz)."""

CROSSING_DTYPE = np.dtype([("ts", "<i8"), ("key", "<i8"), ("frame", "<i8"), ("source", "<i4"), ("stage", "<i2"),
                           ("kind", "<i1")])


def crossings(events: np.ndarray) -> np.ndarray:
    """The crossings of one node's events: each ``link`` event with the ``key`` event written right
    after it (same stage, source and kind), as :data:`CROSSING_DTYPE`. A ``link`` without its
    ``key`` (a trace cut between the two) is left out."""
    point = events["point"]
    at = np.flatnonzero(point[:-1] == LINK) if len(events) > 1 else np.zeros(0, np.int64)
    at = at[point[at + 1] == KEY]
    link, key = events[at], events[at + 1]
    ok = (link["stage"] == key["stage"]) & (link["source"] == key["source"]) & (link["code"] == key["code"])
    link, key = link[ok], key[ok]
    out = np.zeros(len(link), CROSSING_DTYPE)
    out["ts"], out["key"], out["frame"] = link["ts"], key["frame"], link["frame"]
    out["source"], out["stage"], out["kind"] = link["source"], link["stage"], link["code"]
    return out


@dataclass
class Hop:
    """One hop: the frames one node sent and another got, over one transport."""

    name: str
    sender: str
    receiver: str
    transport: str
    delays_ns: list[int] = field(default_factory=list)
    sent_ns: list[int] = field(default_factory=list)
    """When each of those frames was sent (the sender's clock, as corrected)."""
    arrived_ns: list[int] = field(default_factory=list)
    """When each arrived (the receiver's clock, as corrected)."""
    lost_ns: list[int] = field(default_factory=list)
    """When each frame lost on the hop was sent."""
    clock_error_ns: int | None = None
    """The two nodes' correction bounds added up (the largest over the hop's frames); None for
    trace files, whose clocks nothing aligned."""

    @property
    def lost(self) -> int:
        """Frames sent between the first and the last the receiver got, that it never got."""
        return len(self.lost_ns)


@dataclass
class Journey:
    """One frame from its first origin to its end on the last node it reached."""

    start_ns: int
    end_ns: int
    parts: list[tuple[str, int]]
    """(``DCU-1`` or ``net DCU-1 → DCU-2``, ns) in order: the nodes' shares and the hops between."""
    nodes: list[str]
    errors_ns: dict[int, int | None] = field(default_factory=dict)
    """Part index -> a hop's clock error for this frame (both nodes' bounds at its two ends, added;
    None: not aligned)."""

    @property
    def total_ns(self) -> int:
        return self.end_ns - self.start_ns


@dataclass(frozen=True)
class Crossed:
    """One frame joined across a hop: the sent frame (side, source, frame), the arrived one, when."""

    hop: str
    sender: tuple[int, int, int]
    receiver: tuple[int, int, int]
    sent_ns: int
    arrived_ns: int
    error_ns: int | None


@dataclass
class Joined:
    hops: dict[str, Hop]
    journeys: list[Journey]
    untraced: dict[str, int]
    """Per receiving node: frames that arrived with no traced sender's frame to join."""
    ambiguous: dict[str, int]
    crossed: list[Crossed] = field(default_factory=list)
    """Every frame joined across a hop (the exports draw them)."""


def hop_name(transport: str, sender: str, receiver: str) -> str:
    return f"{transport} {sender} → {receiver}"


class Spans:
    """Each frame's first (origin or capture) and last timestamp on one node."""

    def __init__(self, at: dict[tuple[int, int], tuple[int, int]]) -> None:
        self._at = at

    @classmethod
    def of(cls, source: np.ndarray, frame: np.ndarray, first: np.ndarray, last: np.ndarray) -> Spans:
        return cls({(int(a), int(b)): (int(x), int(y)) for a, b, x, y in zip(source, frame, first, last)})

    @classmethod
    def from_events(cls, events: np.ndarray) -> Spans:
        point = events["point"]
        mine = events[(point == ORIGIN) | (point == CAPTURE) | (point == ENTER) | (point == EXIT)]
        order = np.lexsort((mine["frame"], mine["source"]))
        s, f, ts = mine["source"][order], mine["frame"][order], mine["ts"][order]
        new = np.ones(len(order), bool)
        new[1:] = (s[1:] != s[:-1]) | (f[1:] != f[:-1])
        starts = np.flatnonzero(new)
        if not len(starts):
            return cls({})
        return cls.of(s[starts], f[starts], np.minimum.reduceat(ts, starts), np.maximum.reduceat(ts, starts))

    def span(self, source: int, frame: int) -> tuple[int, int] | None:
        return self._at.get((source, frame))


@dataclass
class Side:
    """One node in a join: its name, its crossings (on the clock the join compares), each of its
    frames' span (called only for frames that crossed), and its clock's bound at a time (None:
    not aligned)."""

    name: str
    crossings: np.ndarray
    spans: Callable[[], Spans | None]
    bound: Callable[[int], int | None] = lambda ts: None


def sides_of(traces: list, names: list[str] | None = None) -> list[Side]:
    """The sides of trace files or stored runs (objects with ``header`` and ``events``; a stored
    run's ``correction`` bounds its clock). ``names``: each one's node name as the statistics show
    it (default the headers', told apart as :mod:`dcuscope.model.names` does)."""
    names = names or unique_names(t.header.node for t in traces)
    out = []
    for name, t in zip(names, traces):
        correction = getattr(t, "correction", None)
        bound = (lambda ts: None) if correction is None else (lambda ts, c=correction: int(c.at(ts)[1]))
        out.append(Side(name, crossings(t.events), lambda events=t.events: Spans.from_events(events), bound))
    return out


def join(traces: list, names: list[str] | None = None, window_ns: int = JOIN_WINDOW_NS) -> Joined:
    """:func:`join_sides` of trace files or stored runs (:func:`sides_of`)."""
    return join_sides(sides_of(traces, names), window_ns)


def join_sides(sides: list[Side], window_ns: int = JOIN_WINDOW_NS, newest: int | None = None) -> Joined:
    """Each arriving frame joined to the one sent frame of its key within ``window_ns``; hops,
    losses and the journeys of the frames that end a chain (``newest``: of that many of the
    frames that arrived last, at most: a journey is walked frame by frame)."""
    names, cross = [side.name for side in sides], [side.crossings for side in sides]
    sent: dict[int, list[tuple[int, int, int, int, int, int]]] = defaultdict(list)
    for i, c in enumerate(cross):
        for ts, key, frame, source, stage, kind in c[np.isin(c["kind"], SENT_KINDS)].tolist():
            sent[key].append((ts, i, stage, source, frame, kind))
    hops: dict[str, Hop] = {}
    untraced: dict[str, int] = defaultdict(int)
    ambiguous: dict[str, int] = defaultdict(int)
    came_from: dict[tuple[int, int, int], list[tuple]] = {}
    """(receiver side, source, frame) -> the sent frames it is, with (t_out, t_in, hop name)."""
    crossed: list[Crossed] = []
    got: dict[tuple[int, int, int, str], set[int]] = defaultdict(set)
    """(sender side, its stage, receiver side, transport) -> the send times the receiver got."""
    for r, c in enumerate(cross):
        for ts, key, frame, source, stage, kind in c[np.isin(c["kind"], ARRIVED_KINDS)].tolist():
            transport = LINK_TRANSPORT[kind]
            near = [s for s in sent.get(key, ()) if LINK_TRANSPORT[s[5]] == transport and abs(ts - s[0]) <= window_ns
                    and (s[1] != r or s[2] != stage)]
            sends = {(s[0], s[1], s[2]) for s in near}
            if not sends:
                untraced[names[r]] += 1
                continue
            if len(sends) > 1:
                ambiguous[names[r]] += 1
                continue
            t_out, i, s_stage = next(iter(sends))
            name = hop_name(transport, names[i], names[r])
            hop = hops.setdefault(name, Hop(name, names[i], names[r], transport))
            hop.delays_ns.append(ts - t_out)
            hop.sent_ns.append(t_out)
            hop.arrived_ns.append(ts)
            bounds = (sides[i].bound(t_out), sides[r].bound(ts))
            error = None if None in bounds else bounds[0] + bounds[1]
            if error is not None:
                hop.clock_error_ns = max(hop.clock_error_ns or 0, error)
            got[(i, s_stage, r, transport)].add(t_out)
            came_from[(r, source, frame)] = [(i, s[3], s[4], t_out, ts, name, error) for s in near]
            crossed += [Crossed(name, (i, s[3], s[4]), (r, source, frame), t_out, ts, error) for s in near]
    for (i, stage, r, transport), times in got.items():
        c = cross[i]
        mine = np.unique(c["ts"][(c["stage"] == stage) & np.isin(c["kind"], SENT_KINDS)])
        inside = mine[(mine >= min(times)) & (mine <= max(times))]
        hop = hops[hop_name(transport, names[i], names[r])]
        hop.lost_ns += [t for t in inside.tolist() if t not in times]
    return Joined(hops, _journeys(sides, came_from, newest), dict(untraced), dict(ambiguous), crossed)


def _journeys(sides: list[Side], came_from: dict, newest: int | None = None) -> list[Journey]:
    involved = {k[0] for k in came_from} | {s[0] for v in came_from.values() for s in v}
    spans = [side.spans() if i in involved else None for i, side in enumerate(sides)]
    names = [side.name for side in sides]
    sent_on = {(i, s, f) for i, side in enumerate(sides)
               for s, f in side.crossings[np.isin(side.crossings["kind"], SENT_KINDS)][["source", "frame"]].tolist()}
    out = []
    ends = list(came_from)
    if newest is not None:  # the frames that arrived last (each came_from entry: (..., t_in, ...))
        ends = sorted(ends, key=lambda k: came_from[k][0][4])[-newest:]
    for end in ends:
        if end in sent_on:
            continue  # not the end of its chain: the frame it became has the journey
        journey = _walk(end, came_from, spans, names)
        if journey is not None:
            out.append(journey)
    out.sort(key=lambda j: j.start_ns)
    return out


def _walk(end: tuple[int, int, int], came_from: dict, frames: list, names: list[str]) -> Journey | None:
    """Back from the frame ``end`` to its first origin; None where a frame on the way left no span."""
    r, source, frame = end
    span = frames[r].span(source, frame) if frames[r] is not None else None
    if span is None:
        return None
    end_ns, parts, nodes, here, errors = span[1], [], [names[r]], end, []
    left, start_ns, seen = end_ns, span[0], {end}
    """``left``: when the frame left the node ``here`` (sent on), or ended there."""
    while here in came_from:
        # The frame it was made of that started first (a composite: the earliest of its inputs).
        best = None
        for i, s, f, t_out, t_in, name, error in came_from[here]:
            sp = frames[i].span(s, f) if frames[i] is not None else None
            if sp is not None and (best is None or sp[0] < best[0][0]):
                best = (sp, i, s, f, t_out, t_in, name, error)
        if best is None:
            return None
        sp, i, s, f, t_out, t_in, name, error = best
        parts.append((names[here[0]], left - t_in))
        parts.append((name, t_in - t_out))
        errors.append(error)
        left, here, start_ns = t_out, (i, s, f), sp[0]
        if here in seen:
            return None
        seen.add(here)
        nodes.append(names[i])
    parts.append((names[here[0]], left - start_ns))
    parts.reverse()
    errors.reverse()  # one per hop: the hops are parts 1, 3, 5...
    return Journey(start_ns, end_ns, parts, nodes[::-1], {2 * k + 1: e for k, e in enumerate(errors)})


def journeys_document(joined: Joined) -> dict:
    """The ``journeys`` entry of the statistics: per hop its delays (ms), lost frames and clock
    error; per path of nodes (``DCU-1 → DCU-2``) the journeys' end-to-end delays and each part's,
    whose means add up to the journey's."""
    hops = {}
    for name, hop in joined.hops.items():
        hops[name] = {**summarize(np.asarray(hop.delays_ns, np.float64) / NS_PER_MS), "lost": hop.lost,
                      "clock_error_ms": None if hop.clock_error_ns is None else hop.clock_error_ns / NS_PER_MS,
                      "from": hop.sender, "to": hop.receiver, "transport": hop.transport}
    by_path: dict[str, list[Journey]] = defaultdict(list)
    for j in joined.journeys:
        by_path[" → ".join(j.nodes)].append(j)
    paths = {}
    for path, journeys in by_path.items():
        parts = np.array([[ns for _, ns in j.parts] for j in journeys], np.float64) / NS_PER_MS
        paths[path] = {**summarize(np.array([j.total_ns for j in journeys], np.float64) / NS_PER_MS),
                       "parts": {name: summarize(parts[:, i]) for i, (name, _) in enumerate(journeys[0].parts)}}
    return {"hops": hops, "paths": paths, "untraced": joined.untraced, "ambiguous": joined.ambiguous}
