# Two entry points, both self-installing on a fresh machine with only Python 3.11:
#   make up    set everything up, then run the main job (`hammer up`, default cn3 HAMMER, loopback)
#   make test  set everything up, then run the test suite
# torch is installed first and pinned to the CPU wheel (2.13.0); the project's range admits it,
# so pip never resolves a multi-GB CUDA build.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup up test bench lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

up: $(STAMP)
	$(VENV)/bin/hammer up $(ARGS)

test: $(STAMP)
	$(PY) -m pytest -q $(ARGS)

bench: $(STAMP)
	$(VENV)/bin/hammer bench $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info
