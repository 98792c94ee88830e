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


def every_parser(parser: argparse.ArgumentParser, name: str = "dcuscope"):
    """(name, parser) of ``parser`` and of every subcommand under it, nested ones too (``db migrate``)."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, p in action.choices.items():
                yield from every_parser(p, f"{name} {sub}")


@pytest.mark.parametrize("columns, most", [("300", 100), ("72", 72)])
def test_every_help_line_wraps_at_the_terminal_width_and_at_100_columns_off_a_terminal(monkeypatch, columns, most):
    monkeypatch.setenv("COLUMNS", columns)  # pytest's stdout is no terminal: 300 is capped at 100
    long = [(name, line) for name, p in every_parser(build_parser()) for line in p.format_help().splitlines()
            if len(line) > most]
    assert long == []


def test_a_wrapped_example_still_runs_and_a_hand_written_usage_wraps_whole_groups(monkeypatch):
    monkeypatch.setenv("COLUMNS", "60")
    text = subcommands()["plugin-path"].format_help()
    example = text[text.index("example:"):text.index("  dcuscope stats dcu1")].splitlines()[1:]
    assert len(example) > 3 and all(line.endswith(" \\") for line in example[:-1]), example
    assert " ".join(line.strip().removesuffix(" \\") for line in example) == (
        'GST_PLUGIN_PATH="$(dcuscope plugin-path)" GST_TRACERS="dcuscope(node=DCU-1,trace=dcu1.trace.jsonl)" '
        "gst-launch-1.0 videotestsrc num-buffers=300 ! videoconvert ! x264enc ! fakesink")
    monkeypatch.setenv("COLUMNS", "64")  # the widest group, 38 characters, fits after the 22 of "usage: dcuscope trace"
    usage = subcommands()["trace"].format_usage()
    assert "[--relay-cert FILE [--relay-key FILE]]" in usage.replace("\n", " ")
    assert len(usage.splitlines()) > 2 and all(len(line) <= 62 for line in usage.splitlines()), usage


def test_stored_runs_are_found_with_dcuscope_sessions_and_runs_not_the_http_api():
    parsers = dict(every_parser(build_parser()))
    assert [name for name, p in parsers.items() if "/api/sessions" in p.format_help()] == []
    for name in ("dcuscope stats", "dcuscope export", "dcuscope compare"):
        text = " ".join(parsers[name].format_help().split())
        assert "dcuscope sessions --db DB" in text and "dcuscope runs --db DB" in text, name
