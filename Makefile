# Every target creates .venv on first use: on a fresh machine `make process` and
# `make test` are all a newcomer types.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
VIDEO_DIR ?=
DEMO_DIR := recordings/demo
ARGS ?=

.PHONY: venv process demo test lint bench clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	@test -f $(DEMO_DIR)/calibration.toml || $(PY) -m pipeline synth $(DEMO_DIR) --frames 900

ifeq ($(strip $(VIDEO_DIR)),)
process: demo
	$(PY) -m pipeline process $(DEMO_DIR) --out recordings --force $(ARGS)
else
process: $(STAMP)
	$(PY) -m pipeline process "$(VIDEO_DIR)" --out recordings $(ARGS)
endif

lint: $(STAMP)
	$(VENV)/bin/ruff check pipeline tests
	$(VENV)/bin/mypy pipeline

test: lint
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) -m pipeline.bench $(ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
