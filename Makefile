# `make demo` and `make test` each set up everything on a fresh machine, then run.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test setup clean bench

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	bash scripts/setup_system.sh
	@# torch first, and exactly this version when missing: any other spec pulls CUDA wheels here.
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[test,video,raster]"
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(BIN)/omnirecon demo --out outputs/demo

test: setup
	$(BIN)/python -m pytest -q -ra tests

bench: setup
	$(BIN)/python bench/run_all.py

clean:
	rm -rf $(VENV) outputs
