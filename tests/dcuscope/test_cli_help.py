"""Every option of every ``dcuscope`` command says what it does and, where it has one, its default."""

from __future__ import annotations

import argparse

import pytest

from dcuscope.cli import build_parser
from tests.conftest import run_cli


def subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def undocumented(parser: argparse.ArgumentParser) -> list[str]:
    """Options without help text, or with a default their help does not give."""
    missing = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS:
            continue
        name = action.option_strings[-1] if action.option_strings else action.dest
        if not action.help:
            missing.append(f"{name}: no help text")
        elif has_default(action) and "default" not in action.help.lower():
            missing.append(f"{name}: default {action.default!r} not given")
    return missing


def has_default(action: argparse.Action) -> bool:
    """A default worth telling: not nothing, and not the off state of an on/off flag."""
    flag = isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction))
    return not flag and action.default is not None and action.default != argparse.SUPPRESS


@pytest.mark.parametrize("command", sorted(subcommands()))
def test_every_option_has_help_and_its_default(command):
    assert undocumented(subcommands()[command]) == []


def test_relay_help_describes_the_log_level_and_the_clock_default():
    result = run_cli("relay", "--help", timeout=60)
    assert result.returncode == 0, result.stderr
    text = " ".join(result.stdout.split())
    assert "--log-level" in text and "how much the relay logs to stderr" in text and "(default WARNING)" in text, text
    assert "(default auto)" in text, text


def test_run_help_gives_both_clock_aids_as_testing_aids_and_relay_help_the_clock_port():
    run = " ".join(run_cli("run", "--help", timeout=60).stdout.split())
    assert "--clock-offset-ms MS TESTING AID: " in run and "--clock-drift-ppm PPM TESTING AID: " in run, run
    relay = " ".join(run_cli("relay", "--help", timeout=60).stdout.split())
    assert "--clock-port N" in relay and "0 turns it off" in relay and "clock_packets_per_s" in relay, relay
