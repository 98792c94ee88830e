#!/usr/bin/env bash
# The whole test suite, as `make test` runs it: first every test not marked `alone` in parallel
# workers (pytest-xdist; most tests wait on real time: pipelines at their frame rate, relays,
# browsers), then the tests marked `alone` one at a time, since their assertions need the machine
# to themselves. Both parts always run; the exit status is non-zero if either failed.
#   WORKERS=N   parallel workers (default 6: on 2 cores the suite is mostly waiting)
#   any arguments are passed to both pytest runs (e.g. -x, -k NAME, a test path)
set -uo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
WORKERS=${WORKERS:-6}

say() { printf '\033[1mtest:\033[0m %s\n' "$*"; }

started=$SECONDS
say "parallel part: $WORKERS workers, tests not marked alone"
# loadgroup: tests that share a module-scoped fixture go to one worker (tests/conftest.py),
# every other test to whichever worker is free
$PY -m pytest -q -n "$WORKERS" --dist loadgroup -m "not alone" --durations=10 "$@"
parallel=$?
parallel_s=$((SECONDS - started))

say "alone part: tests marked alone, one at a time"
# Without arguments only the files that mark tests alone are collected (all ~1,100 tests again: ~5 s)
alone_files=()
if [ $# -eq 0 ]; then mapfile -t alone_files < <(grep -rlE 'mark\.alone' tests --include='test_*.py' | sort); fi
$PY -m pytest -q -p no:xdist -m alone --durations=5 "${alone_files[@]}" "$@"
alone=$?
# 5: no tests collected (e.g. a -k that selects none of them) is not a failure
if [ $alone -eq 5 ]; then alone=0; fi
if [ $parallel -eq 5 ]; then parallel=0; fi

say "parallel part $( [ $parallel -eq 0 ] && echo passed || echo FAILED ) in ${parallel_s} s," \
    "alone part $( [ $alone -eq 0 ] && echo passed || echo FAILED ) in $((SECONDS - started - parallel_s)) s"
[ $parallel -eq 0 ] && [ $alone -eq 0 ]
