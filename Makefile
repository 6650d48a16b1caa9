# Two commands on a fresh clone:  `make demo` (the main job) and `make test` (the suite).
# Both create .venv/ on first use and reuse it afterwards.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.esgs-installed
PYTEST_ARGS ?=

.PHONY: setup lint test demo bench clean-venv

setup: $(STAMP)

# torch==2.13.0 first: on this machine kind it is a local CPU build, and installing it
# before the rest keeps pip from pulling a multi-GB CUDA build for a looser range.
$(STAMP): requirements.txt pyproject.toml setup.py
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q torch==2.13.0
	$(PY) -m pip install --disable-pip-version-check -q -r requirements.txt
	$(PY) -m pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e .
	# LPIPS weights (offline afterwards); without them metrics say why instead of guessing
	-$(PY) -m esgs.core.metrics.lpips --fetch
	@touch $(STAMP)

# ruff's configuration is in pyproject.toml; the layer rules are a test (tests/core/test_layers.py)
lint: setup
	$(PY) -m ruff check .

test: lint
	$(PY) -m pytest $(PYTEST_ARGS)

demo: setup
	$(PY) -m esgs.core demo $(DEMO_ARGS)

clean-venv:
	rm -rf $(VENV)
