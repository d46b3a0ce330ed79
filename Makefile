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

.PHONY: setup test demo default-model
setup: $(BIN)/.installed

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q -rs

demo: $(BIN)/.installed
	$(BIN)/streamer serve --source demo --loop --ws 127.0.0.1:8765 --osc 127.0.0.1:39539 --http 8080

# Retrain the embedded default model (see MODEL_CARD.md): the realtime preset on the ZEGGS sample clip
# (last 15 s held out), one CPU thread (deterministic; ~12 min), then copy its inference files into the
# package with its sampling defaults (K = 1, 3 Hz output smoothing; MODEL_CARD.md says why).
ZEGGS ?= ../shared/data/zeggs_sample
default-model: $(BIN)/.installed
	OMP_NUM_THREADS=1 $(BIN)/dimgestor train --data $(ZEGGS) --preset realtime --out runs/default \
		--max-steps 2000 --window-s 5 --batch-size 8 --threads 1 --ckpt-every 250 --valid-every 250 --seed 0 \
		--valid-seconds 15 --vel-weight 5
	$(BIN)/dimgestor export --checkpoint runs/default --out dimgestor/default_model --sample-steps 1 --smooth 3
