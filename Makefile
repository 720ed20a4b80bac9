# ssp developer commands. `make demo` and `make test` work from a fresh clone: they create
# .venv when it is missing and install the project (with its test extras) into it.
VENV   ?= .venv
PYTHON ?= python3
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.ssp-installed

.PHONY: help install demo test lint typecheck bench clean

help:  ## this list
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | sed 's/:.*## /\t/' | expand -t 12

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install --quiet --disable-pip-version-check -e ".[test]"
	@echo "compiling the estimator's kernels (numba, once)"
	$(PY) -c "from ssp.perception.estimator import compile_kernels; compile_kernels()"
	@touch $(STAMP)

install: $(STAMP)  ## create .venv and install ssp with its test extras

demo: $(STAMP)  ## run the built-in demo (writes ssp-demo/)
	$(VENV)/bin/ssp demo

test: $(STAMP)  ## run the test suite
	$(PY) -m pytest -q

lint: $(STAMP)  ## ruff check and ruff format --check
	$(VENV)/bin/ruff check src tests
	$(VENV)/bin/ruff format --check src tests

typecheck: $(STAMP)  ## mypy on the scene-parsing core ([tool.mypy] in pyproject.toml)
	$(PY) -m mypy

bench: $(STAMP)  ## physics benchmark (writes bench-out/physics/results.json)
	$(VENV)/bin/ssp bench physics --out bench-out/physics

clean:  ## remove the venv and caches (not the hull and kernel caches in ~/.cache/ssp)
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache
