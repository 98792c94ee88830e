#!/usr/bin/env bash
# Fuzz the compiled core (dcuscope/model/c) under AddressSanitizer and UndefinedBehaviorSanitizer:
#
#   scripts/fuzz_core.sh [SECONDS] [SEEDS]     # by hand; default 600 s, seeds written to a temporary folder
#
# With clang and its libFuzzer (Debian: apt install clang libclang-rt-dev), coverage-guided libFuzzer
# runs the harness (tests/model/fuzz/fuzz_core.c) and keeps what it finds new in SEEDS; without, or with
# FUZZ_DRIVER=1, gcc builds the harness with its own driver (random mutations of the seeds), as the test
# suite does for 4 s (tests/model/fuzz/test_fuzz_core.py). A finding aborts with the sanitizer's report
# and a non-zero status. CORE_DIR: the C sources to fuzz (default dcuscope/model/c).
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-600}
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
seeds=${2:-$out/seeds}
core=${CORE_DIR:-dcuscope/model/c}
python=${PYTHON:-.venv/bin/python}
[ -x "$python" ] || python=python3
if [ -z "$(ls -A "$seeds" 2>/dev/null)" ]; then
    "$python" -m tests.model.fuzz.seeds "$seeds" >/dev/null
fi
flags=(-g -O1 -std=gnu11 -fsanitize=address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer -I "$core")
sources=(tests/model/fuzz/fuzz_core.c "$core"/*.c)
clang=$(command -v clang || command -v clang-14 || true)
if [ -z "${FUZZ_DRIVER:-}" ] && [ -n "$clang" ] && "$clang" -fsanitize=fuzzer -x c - -o /dev/null <<<'int LLVMFuzzerTestOneInput(const char *d, long n) { return 0; }' 2>/dev/null; then
    "$clang" "${flags[@]}" -DLIBFUZZER -fsanitize=fuzzer -o "$out/fuzz_core" "${sources[@]}" -lm
    echo "fuzz_core: libFuzzer ($clang), $seconds s, corpus $seeds" >&2
    "$out/fuzz_core" -max_total_time="$seconds" -print_final_stats=1 "$seeds"
else
    "${CC:-gcc}" "${flags[@]}" -o "$out/fuzz_core" "${sources[@]}" -lm
    echo "fuzz_core: gcc with its own driver, $seconds s, seeds $seeds" >&2
    "$out/fuzz_core" "$seconds" "$seeds"/*
fi
