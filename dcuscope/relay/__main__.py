"""``python -m dcuscope.relay [--host H] [--port P] [--db PATH] [--token T] [--clock MODE]``: the relay alone."""

import argparse
import sys

from dcuscope.core import signals
from dcuscope.core.errors import DcuscopeError
from dcuscope.relay.commands import add_relay_arguments, run_relay
from dcuscope.relay.guard.limits import limits_help


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dcuscope.relay", description="dcuscope relay", epilog=limits_help(),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_relay_arguments(parser)
    args = parser.parse_args(argv)
    signals.hold()  # a Ctrl-C while starting stops the relay once it is up
    try:
        return run_relay(args)
    except DcuscopeError as exc:
        print(f"dcuscope relay: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
