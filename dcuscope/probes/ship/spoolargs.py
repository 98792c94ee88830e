"""``--spool DIR``, ``--no-spool``, ``--spool-max SIZE`` of the node commands (``run``, ``trace``,
``ship``), and the spool they give (:mod:`dcuscope.probes.ship.spool`)."""

from __future__ import annotations

import argparse
import logging
import re
from pathlib import Path

log = logging.getLogger(__name__)

_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def parse_size(text: str) -> int:
    """``500M``, ``10G``, ``1.5T``, ``4096`` (bytes): powers of 1024."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([kKmMgGtT]?)(?:i?[bB])?\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r} is no size: write e.g. 500M, 10G or 2T")
    value = int(float(m.group(1)) * _UNITS[m.group(2).lower()])
    if value < 1 << 20:
        raise argparse.ArgumentTypeError("must be at least 1M")
    return value


def _fsync_ms(text: str) -> float:
    value = float(text)
    if not 0 <= value <= 60_000:
        raise argparse.ArgumentTypeError("must be 0 to 60000 ms")
    return value


def add_spool_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    from dcuscope.probes.ship.spool import default_dir  # no numpy: the command line starts fast

    parser.add_argument("--spool", type=Path, metavar="DIR",
                        help="keep every batch on disk here until a relay stored it, so that a relay down, a "
                             f"network cut or a crash loses nothing (default {default_dir()}, "
                             "$XDG_STATE_HOME/dcuscope/spool)")
    parser.add_argument("--no-spool", action="store_true",
                        help="keep unacknowledged events in memory only (lost when the process ends)")
    parser.add_argument("--spool-fsync", type=_fsync_ms, metavar="MS", default=None,
                        help="sync the spool to disk at most every MS milliseconds (default 200: a power loss costs at "
                             "most the last 0.2 s; a crashed or killed process loses nothing written); 0: every batch")
    parser.add_argument("--spool-max", type=parse_size, metavar="SIZE",
                        help="bound the spool folder (all its runs) to SIZE, e.g. 2G; beyond it the oldest "
                             "batches are dropped and counted lost (default 10G, or half the free space if less)")


def spool_from_args(args: argparse.Namespace, say=None, *, relay: str | None = None, token: str | None = None,
                    tls=None):
    """The spool of ``--spool``/``--spool-max``/``--spool-fsync`` (None with ``--no-spool``); a folder
    that cannot be used is said in one line and the run goes on in memory only. With ``relay``, the
    runs spooled there earlier are sent to it in the background (said in one line)."""
    if getattr(args, "no_spool", False):
        return None
    from dcuscope.probes.ship.spool import Spool, default_dir
    from dcuscope.probes.ship.spoolfile import SpoolError

    say = say or (lambda line: log.warning("%s", line))
    try:
        fsync_ms = getattr(args, "spool_fsync", None)
        spool = Spool(args.spool or default_dir(), args.spool_max,
                      **({"fsync_s": fsync_ms / 1000} if fsync_ms is not None else {}))
    except SpoolError as exc:
        say(f"dcuscope: {exc}; events are kept in memory only (--no-spool to say so)")
        return None
    if relay is not None:
        from dcuscope.probes.ship.drain import drain_in_background  # aiohttp and numpy: only when shipping

        drain_in_background(spool, relay, token, tls, say)
    return spool
