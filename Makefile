# The two set-up commands of the README: `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export OPENBLAS_NUM_THREADS := 1

.PHONY: demo test test-all lint bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/jaxcal demo --out demo-output

# Two workers (one per core, a file per worker so compiled functions are reused), no persistent
# XLA cache (entries written by crashed or concurrent processes were read back as segfaults), and
# one rerun of a test only when its worker process crashed (XLA 0.10 CPU compiles crashed
# intermittently here; an ordinary failure is never rerun).
PYTEST_RUN := JAXCAL_NO_CACHE=1 $(BIN)/python -m pytest -n 2 --dist loadfile --reruns 1 --only-rerun crashed

test: $(STAMP)
	$(PYTEST_RUN)

test-all: $(STAMP)
	$(PYTEST_RUN) -m ''

lint: $(STAMP)
	$(BIN)/ruff check jaxcal tests benchmarks

bench: $(STAMP)
	$(BIN)/python benchmarks/fk.py
	$(BIN)/python benchmarks/identify.py

clean:
	rm -rf $(VENV) demo-output .pytest_cache
