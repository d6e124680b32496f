# Two commands set everything up on a fresh machine:
#   make demo   creates .venv, installs the pinned set, runs a small real end-to-end job on CPU
#   make test   creates .venv if needed, runs the tests on CPU
# Needs CPython >= 3.12 (jax 0.11.2); set PYTHON=/path/to/python3.12 to choose one.

VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The installer: uv, pinned, installed into .venv by pip from the package registry (make venv 11-32 s against pip's
# 59-120 s on 2 cores: docs/setup.md). INSTALLER=pip installs with pip alone; so does make, saying so, when uv
# cannot be installed or fails (e.g. a pip.conf index or proxy, which uv does not read). Both install the same set.
UV_VERSION := 0.13.8
INSTALLER ?= uv
# pip compiles every module's bytecode at install (25-33 s of a uv install on 2 cores); uv leaves it to the first
# import, which writes what it imports (~5 s for the demo's), except where PYTHONDONTWRITEBYTECODE is set: there
# nothing is ever written (4.0 s against 1.6 s for `python -m experiments --help`, every time), so uv compiles then.
UV_COMPILE := $(if $(PYTHONDONTWRITEBYTECODE),--compile-bytecode)

# First Python >= 3.12 found: $(PYTHON), python3.12, python3.13, pyenv's 3.12.x/3.13.x, python3.
PYTHON ?= $(shell for p in python3.12 python3.13 $$HOME/.pyenv/versions/3.12*/bin/python $$HOME/.pyenv/versions/3.13*/bin/python python3; do \
	  if command -v $$p >/dev/null 2>&1 && $$p -c 'import sys; sys.exit(sys.version_info < (3, 12))' >/dev/null 2>&1; then command -v $$p; break; fi; done)

.PHONY: demo test commands bench venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	@if [ -z "$(PYTHON)" ]; then echo "error: no Python >= 3.12 found (jax 0.11.2 needs it). Install CPython 3.12 or set PYTHON=/path/to/python3.12" >&2; exit 1; fi
	@echo "using $(PYTHON) ($$($(PYTHON) --version))"
	$(PYTHON) -m venv $(VENV)
	@# setuptools' notice "Editable installation." (every flat-layout editable install gets it; it says nothing
	@# about this project) is the one backend message pip shows once pyproject.toml is right: only it is filtered out.
	@run() { echo "$$*"; "$$@"; }; \
	with_pip() { run $(PY) -m pip install -q --upgrade pip && \
	  run env PYTHONWARNINGS="ignore:Editable installation" $(PY) -m pip install -q -c requirements.lock -e ".[test]"; }; \
	with_uv() { run $(VENV)/bin/uv pip install -q --python $(PY) --upgrade pip && \
	  run $(VENV)/bin/uv pip install -q --python $(PY) $(UV_COMPILE) -c requirements.lock -e ".[test]"; }; \
	if [ "$(INSTALLER)" = pip ]; then echo "installing the pinned set with pip (INSTALLER=pip)"; with_pip; \
	elif [ "$(INSTALLER)" != uv ]; then echo "error: INSTALLER=$(INSTALLER): uv or pip" >&2; exit 2; \
	elif ! run $(PY) -m pip install -q uv==$(UV_VERSION); then \
	  echo "note: uv $(UV_VERSION) could not be installed (above); installing the pinned set with pip (slower)" >&2; \
	  with_pip; \
	else with_uv || { echo "note: uv failed (above); installing the pinned set with pip instead (slower)" >&2; with_pip; }; fi \
	  || { echo "error: the install into $(VENV) failed (above); make again once its cause is fixed" >&2; exit 1; }
	@touch $(STAMP)

demo: $(STAMP)
	JAX_PLATFORMS=cpu $(PY) -m experiments demo

test: $(STAMP)
	$(PY) -m ruff check .
	JAX_PLATFORMS=cpu $(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --durations=25 tests --nbmake --nbmake-timeout=1200 experiments/notebooks

commands: $(STAMP)  # every `python -m experiments` command in its quickest form (long: a GPU host with -n 8)
	$(PY) -m pytest -q -m commands -n $(or $(JOBS),2) tests/test_commands.py

bench: $(STAMP)
	$(PY) -m experiments bench-surrogate

clean:
	rm -rf $(VENV) results .pytest_cache .hypothesis
