# Two entry points, as in the README: `make demo` (main job) and `make test` (the test suite).
# Each sets up its own virtual environment on first use.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[test]'
	touch $@

.PHONY: setup test demo
setup: $(BIN)/.installed

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q -rs

demo: $(BIN)/.installed
	$(BIN)/streamer serve --source demo --ws 127.0.0.1:8765 --osc 127.0.0.1:39539 --http 8080
