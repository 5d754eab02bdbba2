# The two set-up commands of the README: `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export OPENBLAS_NUM_THREADS := 1

.PHONY: demo test test-all lint bench clean

# The install goes through uv where it can be had from the package index. `make .venv/.installed` on a fresh clone, this
# 2-core machine, an empty uv cache, two rounds back to back (2026-11-30): 14.0 and 16.7 s, against 23.8 and 26.9 s
# with pip alone (pip's upgrade, then `pip install -e`, of which ~14 s is pip compiling bytecode one file after another;
# uv compiles on every core). Bytecode is compiled at install because the environment may set PYTHONDONTWRITEBYTECODE
# (this one does): without it every Python process of the tests imports jax, scipy and matplotlib from source, ~2 s
# more each. Without uv (no index, an error) pip installs it all.
INSTALL = $(BIN)/python -m pip install -q uv && $(BIN)/uv pip install -q --python $(BIN)/python --compile-bytecode -e '$(1)' \
	|| $(BIN)/python -m pip install -q -e '$(1)'

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(call INSTALL,.[dev])
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/jaxcal demo --out demo-output

# Two workers (one per core). worksteal hands each worker a contiguous half of the tests, so a
# file's tests mostly share one process and its compiled functions; an idle worker takes work
# from the other's tail. A test that crashes its worker (segfault, abort, or the watchdog of
# tests/conftest.py, which dumps all stacks and exits the process past the test's limit) is
# reported as "worker crashed", the worker is replaced (at most 4 times), and pytest-rerunfailures
# puts the test back in the queue once: `--reruns 1` counts the crash, while `--only-rerun` and
# `--rerun-except` only ever filter ordinary failures; `--rerun-except .` matches every one, so an
# ordinary failure is never rerun. (--dist loadfile cannot put a crashed test back.) --durations: the 20 slowest tests
# are listed at the end (issue 18: where the suite's time goes).
# tests/conftest.py gives the runs of this checkout one cache of compiled code (.cache/test-xla), shared by both
# workers and kept for the next run (a fresh clone starts empty),
# compiles with XLA:CPU's elemental emitter, at LLVM level 0 for the fast run (`-m 'not slow'`: it compiles faster; the
# slow studies run faster at the default level), and has the workers allocate with jemalloc where the system has it
# (Debian's libjemalloc2, which .ci/run installs), docs/benchmarks.md.
PYTEST_RUN := $(BIN)/python -m pytest -n 2 --dist worksteal --max-worker-restart 4 --reruns 1 --rerun-except . --durations=20

test: $(STAMP)
	$(PYTEST_RUN)

test-all: $(STAMP)
	$(PYTEST_RUN) -m ''

lint: $(STAMP)
	$(BIN)/ruff check jaxcal tests benchmarks

BENCH_EXTRAS := .[dev,bench]
$(VENV)/.bench-installed: $(STAMP)
	$(call INSTALL,$(BENCH_EXTRAS))
	touch $@

bench: $(VENV)/.bench-installed
	$(BIN)/python benchmarks/table.py

clean:
	rm -rf $(VENV) demo-output .pytest_cache .cache
