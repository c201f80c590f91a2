# Every target creates .venv on first use: on a fresh machine `make process` and
# `make test` are all a newcomer types.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
VIDEO_DIR ?=
# The session folder reaches the recipe through the environment as it was given: make
# expands a $ in it no further, and the shell reads it from there, so $ and " are kept.
override VIDEO_DIR := $(value VIDEO_DIR)
export VIDEO_DIR
DEMO_DIR := recordings/demo
ARGS ?=

.PHONY: venv process demo test lint bench clean vulkan

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
# The session folder last, after --: one named like an option (-x) is still the folder.
process: $(STAMP)
	$(PY) -m pipeline process --out recordings $(ARGS) -- "$$VIDEO_DIR"
endif

lint: $(STAMP)
	$(VENV)/bin/ruff check pipeline tests
	$(VENV)/bin/mypy pipeline

# The layout's screenshot tests draw with Rerun's headless viewer, which needs a Vulkan
# driver: on a machine without one, Mesa's software driver (apt's mesa-vulkan-drivers,
# about 16 MB), installed where we are root with apt-get. Elsewhere those tests are
# skipped, except under CI=true, where they fail.
vulkan:
	@if ! ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1 && [ "$$(id -u)" = 0 ] \
		&& command -v apt-get >/dev/null; then \
		echo "installing Mesa's software Vulkan driver for Rerun's headless viewer"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
			--no-install-recommends mesa-vulkan-drivers libvulkan1 >/dev/null; \
	fi

# Two pytest workers, each taking whole test files (module fixtures render once).
test: lint vulkan
	$(PY) -m pytest -q -n 2 --dist loadfile

bench: $(STAMP)
	$(PY) -m pipeline.measure.bench $(ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
