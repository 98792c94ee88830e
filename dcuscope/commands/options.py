"""What several commands share on their command lines: value checks, and the node's options for
relays (``--relay``, ``--token``, TLS, the spool, ``--close-timeout``), declared once here for
``dcuscope run``, ``trace`` and ``ship``."""

from __future__ import annotations

import argparse

from dcuscope.probes.ship.nodetls import add_tls_arguments
from dcuscope.probes.ship.spoolargs import add_spool_arguments
from dcuscope.protocol.credentials import NODE_TOKEN_HELP, add_token_argument

CLOSE_TIMEOUT_S = 60.0
"""``--close-timeout``'s default: protocol.events.EXPORTER_CLOSE_S (not imported here: numpy slows the start)."""
MAX_DRIFT_PPM = 1000.0
"""Beyond any quartz (tens of ppm): a larger --clock-drift-ppm is a typo."""


def positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError("must be a positive integer")
    return value


def positive_float(text: str) -> float:
    value = float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError("must be positive")
    return value


def drift_ppm(text: str) -> float:
    value = float(text)
    if not abs(value) <= MAX_DRIFT_PPM:
        raise argparse.ArgumentTypeError(f"must be within +-{MAX_DRIFT_PPM:g} ppm")
    return value


def add_relay_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup, relay_help: str,
                        after: str, keeps: str) -> None:
    """``--relay``, ``--token``, ``--relay-ca/-cert/-key``, the spool's options and ``--close-timeout``:
    ``after`` says when the node waits for acknowledgements (``once CMD ended``), ``keeps`` what still
    holds what is lost then (``TRACE still holds it``)."""
    parser.add_argument("--relay", metavar="URL[,URL...]", help=relay_help)
    add_token_argument(parser, NODE_TOKEN_HELP)
    add_tls_arguments(parser)
    add_spool_arguments(parser)
    parser.add_argument("--close-timeout", type=positive_float, default=CLOSE_TIMEOUT_S, metavar="S",
                        help=f"{after}, keep trying every --relay for up to S seconds until all that was sent is "
                             f"acknowledged, saying what it waits for (default %(default)g); what is still "
                             f"unacknowledged then is reported lost ({keeps})")
