"""``--frame-limit [NODE=]MS``: parsing, precedence and the errors a typo gets."""

from __future__ import annotations

import subprocess
import sys

import pytest

from dcuscope.relay.errors import RelayError
from dcuscope.relay.live.framelimits import FrameLimits


def test_a_node_limit_wins_over_the_default():
    limits = FrameLimits.parse(["250", "DCU-2=400.5", "cam=a=3"])
    assert limits.limit_ns("DCU-1") == 250_000_000
    assert limits.limit_ns("DCU-2") == 400_500_000
    assert limits.limit_ns("cam=a") == 3_000_000  # a node name may hold '='; the last one splits
    assert FrameLimits.parse(["DCU-2=400"]).limit_ns("DCU-1") is None


@pytest.mark.parametrize("spec, says", [("=5", "give MS or NODE=MS"), ("DCU-1=fast", "not a number"),
                                        ("0", "over 0"), ("nan", "over 0"), ("-3", "over 0"), ("1e9", "at most")])
def test_bad_limits_are_named(spec, says):
    with pytest.raises(RelayError, match=says):
        FrameLimits.parse([spec])


def test_the_relay_command_refuses_a_bad_limit_with_exit_2(tmp_path):
    out = subprocess.run([sys.executable, "-m", "dcuscope.cli", "relay", "--port", "0", "--db", str(tmp_path / "r.db"),
                          "--frame-limit", "DCU-1=soon"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr
    assert "--frame-limit 'DCU-1=soon'" in out.stderr and "Traceback" not in out.stderr
