# The README's two commands: `make demo` and `make test`. Both create .venv (Python 3.12) if missing.
SHELL := /bin/bash
# First Python 3.12 found: on PATH, under pyenv, or the system one (pyenv's shim on PATH may point elsewhere).
PY312 ?= $(shell for p in python3.12 $(HOME)/.pyenv/versions/3.12*/bin/python3.12 /usr/local/bin/python3.12 /usr/bin/python3.12; do \
	if $$p -c 'import sys; assert sys.version_info[:2] == (3, 12)' >/dev/null 2>&1; then echo $$p; break; fi; done)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
DEMO_OUT ?= outputs/demo

.PHONY: install browser demo test test-fast test-numerics lint bench results clean

$(STAMP): pyproject.toml requirements-dev.txt $(wildcard plugins/*/pyproject.toml)
	@if [ -z "$(PY312)" ]; then echo "Python 3.12 is required (LeRobot >= 0.5 needs it); none found" >&2; exit 1; fi
	@test -x $(PY) || $(PY312) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements-dev.txt
	@touch $(STAMP)

install: $(STAMP) browser

## Headless Chromium for the explorer's browser test (tests/test_explorer.py, slow): Debian's chromium and
## chromium-driver, installed with apt-get when missing and we are root. Never fails the install: without the
## browser that one test skips and says how to install it.
browser:
	@if command -v chromium >/dev/null 2>&1 && command -v chromedriver >/dev/null 2>&1; then :; \
	elif command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
		echo "installing chromium and chromium-driver (apt-get) for the explorer's browser test"; \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null) \
			|| echo "could not install chromium chromium-driver: the explorer's browser test will skip" >&2; \
	else echo "no chromium/chromedriver: the explorer's browser test skips (as root: apt-get install -y chromium chromium-driver)" >&2; fi

## Main job: generate a dataset, train PDP and a DP baseline with lerobot-train, steer in scenes 0-3, figures.
demo: $(STAMP)
	HF_HUB_OFFLINE=1 $(VENV)/bin/lerobot-pdp benchmark --env reach-around --quick --out $(DEMO_OUT)

## Whole test suite (slow end-to-end tests included), then the numerics-sensitive tests again on other kernels.
## TEST_WORKERS pytest processes side by side (pytest-xdist; one torch thread each; 1 = none). With pytest 9.2
## xdist 3.8's groups do not take (its suffix no longer reaches the test ids): tests are dealt one by one, and
## a session fixture is built once per worker that needs it.
TEST_WORKERS ?= 2
XDIST = $(if $(filter-out 0 1,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadgroup,)
test: $(STAMP) browser
	HF_HUB_OFFLINE=1 $(VENV)/bin/pytest -q -p no:cacheprovider $(XDIST) --durations=15
	@$(MAKE) --no-print-directory test-numerics

## The tests marked `numerics` under other CPU code paths than this machine's: MKL's SSE2 'compatible' kernels, ATen's
## scalar ones, oneDNN's SSE4.1 convolutions. A tolerance that only holds on one CPU's float kernels (another
## vendor or vector width computes the low-order bits differently) fails here on any machine.
NUMERICS_ENV ?= MKL_CBWR=COMPATIBLE ATEN_CPU_CAPABILITY=default ONEDNN_MAX_CPU_ISA=SSE41
test-numerics: $(STAMP)
	HF_HUB_OFFLINE=1 $(NUMERICS_ENV) $(VENV)/bin/pytest -q -p no:cacheprovider $(XDIST) -m numerics

## Contributors' loop: the tests not marked slow (no lerobot-train processes), a few minutes.
test-fast: $(STAMP)
	HF_HUB_OFFLINE=1 $(VENV)/bin/pytest -q -p no:cacheprovider $(XDIST) -m "not slow"

## The full protocol for every env (3 seeds x 40 rollouts, baselines, ablations): hours on 2 CPU cores.
## Resumable: finished (method, seed) runs under RESULTS_OUT are reused.
RESULTS_OUT ?= outputs/full
results: $(STAMP)
	for env in reach-around avoiding pick-place kitchen-microwave; do \
		HF_HUB_OFFLINE=1 $(VENV)/bin/lerobot-pdp benchmark --env $$env --ablations --out $(RESULTS_OUT)/$$env || exit 1; \
	done

lint: $(STAMP)
	$(VENV)/bin/ruff check lerobot_pdp lerobot_policy_pdp plugins tests benchmarks examples scripts

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do HF_HUB_OFFLINE=1 $(PY) $$b; done

clean:
	rm -rf build dist *.egg-info outputs
