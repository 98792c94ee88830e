# dcuscope: the two commands a newcomer needs are `make demo` and `make test`.
PY := .venv/bin/python
DURATION ?=
PORT ?= 3000

.PHONY: setup demo test test-fast bench clean

setup:
	@scripts/setup.sh

demo: setup
	$(PY) -m dcuscope.cli demo --port $(PORT) $(if $(DURATION),--duration $(DURATION))

test: setup
	@scripts/test.sh

test-fast: setup
	$(PY) -m pytest -q -n $${WORKERS:-6} --dist loadgroup -m "not slow and not alone"

bench: setup
	$(PY) benchmarks/bench_pipeline.py
	$(PY) benchmarks/bench_elements.py
	$(PY) benchmarks/bench_probes.py

clean:
	rm -rf .venv dcuscope/probes/capture/_build dcuscope/model/_build dcuscope/ui/node_modules dcuscope/ui/static/vendor .pytest_cache build dist
