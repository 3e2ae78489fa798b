# `make run` and `make test` set up a fresh Debian/Ubuntu host (as root) and then do their job.
VENV := .venv
PY := $(VENV)/bin/python
PORT ?= 9969

.PHONY: setup setup-test run test test-kernels test-chroot bench soak readme lock mixin demo demo-stop clean

setup:
	@scripts/setup.sh

setup-test:
	@DRUMS_SETUP_TEST=1 scripts/setup.sh

run: setup
	$(VENV)/bin/drums agent --port $(PORT)

# Two lanes at once, as they share nothing: the tests that run the demo robot (`make demo`, minutes
# of it, one at a time) and a few other long ones (lane2), to even the lanes out; and all the others.
# A lane with nothing selected (exit 5) is no failure.
test: setup-test
	@$(PY) -m pytest -q -p no:cacheprovider -m demo $(PYTEST_ARGS) >.test-demo.log 2>&1 & demo=$$!; \
	$(PY) -m pytest -q -p no:cacheprovider -m lane2 $(PYTEST_ARGS) >.test-lane2.log 2>&1 & lane2=$$!; \
	$(PY) -m pytest -q -m "not demo and not lane2" $(PYTEST_ARGS); rest=$$?; \
	wait $$lane2; lane2_rc=$$?; echo "--- the second lane:"; cat .test-lane2.log; rm -f .test-lane2.log; \
	wait $$demo; demo_rc=$$?; echo "--- the demo lane:"; cat .test-demo.log; rm -f .test-demo.log; \
	for rc in $$rest $$lane2_rc $$demo_rc; do [ $$rc -eq 0 ] || [ $$rc -eq 5 ] || exit $$rc; done

# The portable tests (marked kernel) on each kernel of tests/kernels/matrix.py, booted under qemu
# (KVM where it works, else emulation: minutes a kernel), and on this host's own; their rows go to
# tests/kernels/results.json and the README's platform table. KERNELS=6.1,5.10 picks some, CI=1
# the ones .ci/run runs, each probe on the path the agent takes only (CI's time), MINUTES_LEFT=N
# starts none that would not end within N minutes.
test-kernels: setup-test
	@DRUMS_SETUP_KERNELS=1 scripts/setup.sh
	$(PY) -m tests.kernels.run $(if $(CI),--ci) $(if $(KERNELS),--kernels $(KERNELS)) $(if $(MINUTES_LEFT),--minutes $(MINUTES_LEFT))
	$(PY) -m tests.kernels.readme README.md

# The whole of make test, from a fresh clone, in a Debian root file system of another release made
# with debootstrap (its Python, bcc and packages; this machine's kernel): SUITE=trixie is Python 3.13.
SUITE ?= trixie
test-chroot:
	@SUITE=$(SUITE) scripts/test-in-chroot.sh

# The monitoring mixin: rules, alerts and dashboards rendered from deploy/mixin/config.yaml into
# deploy/mixin/out (checked in; a test fails when they differ from what the code renders).
mixin: setup-test
	$(PY) -m deploy.mixin.build

# A small robot on this machine, watched by Drums, Prometheus and drums top (demo/demo.sh);
# FAULT=leak|flood|throttle injects one of the paper's faults, FAULT=all the three in turn, with drums
# detect watching. demo-stop ends all of it.
demo: setup-test
	@demo/demo.sh start $(FAULT)

demo-stop:
	@demo/demo.sh stop

# Every benchmark; their tables go to bench/results.json, and from there into the README. NAB=PATH: a
# checkout of github.com/numenta/NAB for bench/nab.py (the detector on the Numenta Anomaly Benchmark).
bench: setup-test
	@DRUMS_SETUP_TEST=1 DRUMS_SETUP_BENCH=1 scripts/setup.sh
	NAB=$(NAB) $(PY) bench/run_all.py
	$(PY) bench/readme.py README.md

# A soak, apart from make bench for its length: the agent under churn for MINUTES (default 30),
# its memory, open files, threads and byte exactness printed every minute.
MINUTES ?= 30
soak: setup-test
	$(PY) bench/soak.py --minutes $(MINUTES)

# The README's metric table is generated from the probes' own declarations, its measured figures
# from bench/results.json.
readme: setup
	$(PY) -m drums.docs README.md
	$(PY) bench/readme.py README.md

# Resolve the dependencies again at their newest versions and pin them, with their hashes, for every
# platform and Python the project supports: requirements-test.lock for the tests (ROS 2 included),
# requirements.lock for the agent alone, held to the same versions. Review the diff, run
# `make test`, commit both.
UV_VERSION := 0.13.8
lock: setup
	$(VENV)/bin/pip install -q --disable-pip-version-check uv==$(UV_VERSION)
	$(VENV)/bin/uv pip compile -q --universal --python-version 3.10 --generate-hashes --upgrade \
		--extra test -o requirements-test.lock pyproject.toml
	$(VENV)/bin/uv pip compile -q --universal --python-version 3.10 --generate-hashes \
		-c requirements-test.lock -o requirements.lock pyproject.toml

clean:
	-$(VENV)/bin/drums unload 2>/dev/null
	rm -rf $(VENV) .pytest_cache
