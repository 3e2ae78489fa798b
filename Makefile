# `make run` and `make test` set up a fresh Debian/Ubuntu host (as root) and then do their job.
VENV := .venv
PY := $(VENV)/bin/python
PORT ?= 9969

.PHONY: setup setup-test run test bench readme clean

setup:
	@scripts/setup.sh

setup-test:
	@DRUMS_SETUP_TEST=1 scripts/setup.sh

run: setup
	$(VENV)/bin/drums agent --port $(PORT)

test: setup-test
	$(PY) -m pytest -q $(PYTEST_ARGS)

bench: setup-test
	$(PY) bench/run_all.py

# The README's metric table is generated from the probes' own declarations.
readme: setup
	$(PY) -m drums.docs README.md

clean:
	-$(VENV)/bin/drums unload 2>/dev/null
	rm -rf $(VENV) .pytest_cache
