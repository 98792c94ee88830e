"""benchmarks/figures.py: a figure a run could not produce is n/a with its reason, through
arithmetic, statistics, formatting, tables and JSON; a benchmark that cannot run says so in one line."""

from __future__ import annotations

import json
import math

import pytest

from benchmarks.figures import (
    NA, CannotRun, Notes, dumps, fmt, known, last_line, maximum, mean, median, minimum, missing, percentile, ratio,
    run,
)
from tests.benchmarks.smoke import assert_every_na_has_a_reason

WHY = "no batch acknowledged in the window"


def test_an_na_shows_its_reason_and_goes_through_arithmetic_and_formatting():
    x = NA(WHY)
    assert str(x) == f"n/a ({WHY})" and f"{x:8.1f}" == f"n/a ({WHY})" and not x
    assert 100 * x is x and x / 2 is x and 1 - x is x and -x is x and round(x, 3) is x and round(x) is x
    assert NA("a\n  b") == NA("a b") and NA("").reason == "no reason given"
    with pytest.raises(TypeError):
        x < 1  # noqa: B015 - a comparison must not pass silently
    with pytest.raises(TypeError):
        float(x)


def test_statistics_of_nothing_are_na_with_the_reason_given_or_that_of_their_inputs():
    assert median([]) == NA("no value to take the median of")
    assert median([], "no run of arm a") == NA("no run of arm a")
    assert mean([None, math.nan], "nothing") == NA("nothing")
    assert percentile([], 99, "no frame reached the client") == NA("no frame reached the client")
    assert minimum([], "x") == NA("x") and maximum([], "y") == NA("y")
    # the inputs' own reasons win over the generic one, each once
    assert median([NA("too short"), None, NA("too short"), NA("relay down")], "generic") == NA("too short; relay down")
    # figures among missing values are used
    assert median([3, None, NA(WHY), 1, 2]) == 2 and mean([1, 3, math.nan]) == 2.0
    assert percentile([1, 2, 3, 4, 5], 50) == 3.0 and minimum([2, None, 1]) == 1 and maximum([NA(WHY), 4]) == 4


def test_a_ratio_with_a_zero_or_missing_operand_is_na():
    assert ratio(1, 4) == 0.25
    assert ratio(1, 0, "the relay used no CPU") == NA("the relay used no CPU")
    assert ratio(NA(WHY), 0) == NA(WHY) and ratio(3, NA(WHY)) == NA(WHY)
    assert ratio(None, 2, missing_reason="no rate") == NA("no rate") and ratio(1, math.nan) == NA("not measured")
    assert missing(None) and missing(math.nan) and missing(NA(WHY)) and not missing(0) and not missing(0.0)
    assert known(0, "x") == 0 and known(None, "x") == NA("x") and known(NA(WHY), "x") == NA(WHY)


def test_fmt_gives_the_figure_or_n_a_with_its_reason():
    assert fmt(12.345, ".1f", " ms") == "12.3 ms"
    assert fmt(NA(WHY), ".1f", " ms") == f"n/a ({WHY})"
    assert fmt(None, ".1f", why="no p95 of the frame delay") == "n/a (no p95 of the frame delay)"
    assert fmt(None) == "n/a (not measured)"


def test_notes_number_each_reason_once_and_list_them_under_the_table():
    notes = Notes()
    assert not notes and notes.lines() == []
    cells = [notes.cell(1.234, ".1f"), notes.cell(NA(WHY)), notes.cell(None, why="no run of arm a"),
             notes.cell(NA(WHY)), notes.cell(5, "g", " %")]
    assert cells == ["1.2", "n/a [1]", "n/a [2]", "n/a [1]", "5 %"] and notes
    assert notes.lines() == [f"n/a [1]: {WHY}", "n/a [2]: no run of arm a"]
    assert_every_na_has_a_reason("\n".join(["| " + " | ".join(cells) + " |", "", *notes.lines()]))


def test_json_has_every_na_as_its_text():
    text = dumps({"rate": NA(WHY), "lag": [1.5, NA("no frame")], "n": 2})
    assert json.loads(text) == {"rate": f"n/a ({WHY})", "lag": [1.5, "n/a (no frame)"], "n": 2}
    with pytest.raises(TypeError):
        dumps({"x": object()})


def test_the_na_check_of_the_smoke_tests_finds_an_n_a_without_its_reason():
    assert_every_na_has_a_reason(f"a n/a ({WHY}) b n/a [1] c\n\nn/a [1]: {WHY}\n")
    for bad in ("lost: n/a", "lost: n/a ()", "lost: n/a [2]\nn/a [1]: x", "| n/a [1] |\nn/a [1]: "):
        with pytest.raises(AssertionError):
            assert_every_na_has_a_reason(bad)


def test_a_benchmark_that_cannot_run_says_why_in_one_line_with_status_2(capsys):
    def main() -> int:
        raise CannotRun("/usr/bin/prometheus is missing:\n  install Debian's prometheus")

    assert run(main, "bench_x.py") == 2
    err = capsys.readouterr().err
    assert err == "bench_x.py: cannot run: /usr/bin/prometheus is missing: install Debian's prometheus\n"
    assert run(lambda: 1) == 1 and run(lambda: None) == 0


def test_last_line_is_the_error_not_the_traceback():
    assert last_line(b"Traceback (most recent call last):\n  File x\nOSError: port taken\n\n") == "OSError: port taken"
    assert last_line("") == "(no output)"
