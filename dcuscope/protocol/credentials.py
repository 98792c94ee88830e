"""The credential a node presents to a relay, and where both look for it by default."""

import os

TOKEN_ENV = "DCUSCOPE_TOKEN"
"""The environment variable a node's ``--token`` (and the relay's) defaults to: a secret given on a
command line is in every process listing."""
NODE_TOKEN_HELP = f"the relay's node token, if it asks for one (default ${TOKEN_ENV}, which keeps it out of process listings)"


def add_token_argument(parser, help: str) -> None:  # noqa: A002 - argparse's own word
    """``--token TOKEN``, by default ``$DCUSCOPE_TOKEN``: the node's credential, or the relay's admin token."""
    parser.add_argument("--token", metavar="TOKEN", default=os.environ.get(TOKEN_ENV), help=help)
