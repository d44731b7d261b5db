# Set-up and entry points. `make run` and `make test` do all set-up on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
BUILDING ?= demo
BIN = $(VENV)/bin
STAMP = $(VENV)/.installed

.PHONY: setup run test lint clean-data

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/ensure_system_deps.sh
	bash scripts/ensure_system_deps.sh
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

## the whole DAG on one building (default: demo); e.g. `make run BUILDING=synthetic64`
run: $(STAMP)
	$(BIN)/doit building=$(BUILDING)

## the test suite (the viewer's browser test needs chromium: installed here where apt allows)
test: $(STAMP)
	bash scripts/ensure_browser.sh
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check .

clean-data:
	rm -rf data/$(BUILDING)
