"""``python -m dcuscope ...``: the same as the ``dcuscope`` command."""

import sys

from dcuscope.cli import main

sys.exit(main())
