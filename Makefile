# Two entry points, as in the README: `make demo` (main job) and `make test` (the test suite).
# Each sets up the virtual environment it needs on first use (docs/install.md): `make demo` only what serving
# needs, `make test` the test tools besides; each step is remembered by a stamp file in the environment.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
PIP := $(BIN)/python -m pip install -q --disable-pip-version-check
# The torch build (scripts/install-torch): auto (the CPU build on Linux without an NVIDIA GPU, PyPI's default
# elsewhere), cpu, cuda or default. To switch an existing environment: make torch TORCH=cuda
TORCH ?= auto
export TORCH

$(BIN)/python:
	@echo "Creating the virtual environment $(VENV) ($(PYTHON) -m venv)"
	@$(PYTHON) -m venv $(VENV)
	@$(PIP) --upgrade pip

# (order-only: the interpreter is a link whose time is the system Python's)
$(VENV)/.torch-installed: pyproject.toml scripts/install-torch | $(BIN)/python
	@sh scripts/install-torch $(BIN)/python
	@touch $@

$(VENV)/.serve-installed: pyproject.toml $(VENV)/.torch-installed
	@echo "Installing dimgestor and what serving needs (pip install -e .)"
	@$(PIP) -e .
	@touch $@

# `dimgestor export-onnx` and `--backend onnxruntime` (make web exports the model).
$(VENV)/.onnx-installed: pyproject.toml $(VENV)/.serve-installed
	@echo "Installing the ONNX exporter and runtime (pip install -e '.[onnx]')"
	@$(PIP) -e '.[onnx]'
	@touch $@

# The test extra holds the onnx extra's pins too: after it, `make demo` and `make web` install nothing more.
$(VENV)/.test-installed: pyproject.toml $(VENV)/.torch-installed
	@echo "Installing dimgestor with its test tools (pip install -e '.[test]')"
	@$(PIP) -e '.[test]'
	@echo "Installing openwakeword 0.5.1 without its dependencies, for the embedding front end's two ONNX files"
	@$(PIP) --no-deps openwakeword==0.5.1
	@touch $@ $(VENV)/.serve-installed $(VENV)/.onnx-installed

# Test tooling from npm, pinned by tests/node/package-lock.json: an independent OSC parser for the VMC checks and the
# Khronos glTF validator for exported animation. Without npm the tests that need them skip and say so.
VMC_CHECK := tests/node
$(VMC_CHECK)/node_modules/.package-lock.json: $(VMC_CHECK)/package.json $(VMC_CHECK)/package-lock.json
	@if command -v npm >/dev/null; then cd $(VMC_CHECK) && npm ci --omit=optional --no-audit --no-fund --loglevel=error; \
	else echo "npm not found: the VMC receiver and glTF validator checks in $(VMC_CHECK) will be skipped (Debian: apt install npm)" >&2; fi

# The web viewer's JavaScript dependencies (three.js, three-vrm; three-vrm-animation for the tests' VRMA checks) from
# npm, pinned by clients/web/package-lock.json; the viewer's HTTP server serves them from clients/web/node_modules
# (no CDN, no internet at run time).
WEB := clients/web
$(WEB)/node_modules/.package-lock.json: $(WEB)/package.json $(WEB)/package-lock.json
	@if command -v npm >/dev/null; then echo "Installing the web viewer's three.js and three-vrm (npm ci in $(WEB))"; \
		cd $(WEB) && npm ci --no-audit --no-fund --loglevel=error; \
	else echo "npm not found: the browser viewer cannot load three.js and its tests will be skipped (Debian: apt install npm)" >&2; fi

.PHONY: setup torch test demo default-model live-model web
# What `make demo` needs: torch, the package and its dependencies, the viewer's JavaScript.
setup: $(VENV)/.serve-installed $(WEB)/node_modules/.package-lock.json

torch: | $(BIN)/python
	sh scripts/install-torch $(BIN)/python
	@touch $(VENV)/.torch-installed

# --max-worker-restart 0: a test process that crashes ends the run with that test failed (pytest-xdist 3.8 replacing
# a crashed worker under --dist loadfile can wait forever at the end of the run: pytest-xdist issues 784, 1378).
test: $(VENV)/.test-installed $(WEB)/node_modules/.package-lock.json $(VMC_CHECK)/node_modules/.package-lock.json
	$(BIN)/python -m pytest -q -rs -n 2 --dist loadfile --no-loadscope-reorder --max-worker-restart 0 --durations=30

# Ports of `make demo`, e.g. `make demo WS_PORT=9000 OSC_PORT=39540` (the viewer: http://127.0.0.1:WS_PORT/).
WS_PORT ?= 8765
OSC_PORT ?= 39539
demo: setup
	@echo "Starting the server: open http://127.0.0.1:$(WS_PORT)/ (VMC to 127.0.0.1:$(OSC_PORT)); Ctrl-C stops"
	$(BIN)/dimgestor serve --source demo --loop --ws 127.0.0.1:$(WS_PORT) --vmc 127.0.0.1:$(OSC_PORT)

# The viewer with the model running in the browser (onnxruntime-web), no inference server: exports the default
# model into web-model/ the first time; then open http://127.0.0.1:WEB_PORT/?local=model/
WEB_PORT ?= 8766
web: $(VENV)/.onnx-installed $(WEB)/node_modules/.package-lock.json
	$(BIN)/dimgestor web --model web-model --port $(WEB_PORT)

# Retrain the embedded default model (see MODEL_CARD.md): the realtime preset with the speech front end
# (level-free bands and prosody), 300 ms of audio lookahead (downsampler kernel 41) and 15 % condition dropout,
# on the ZEGGS sample clip (last 15 s held out) with the default "streaming" recipe (mirroring and 0.9x/1.1x
# speed perturbation on, as for any small set; audio augmentation off: it did not raise the unseen-voice
# coupling on this clip), one CPU thread (deterministic; ~12 min on a quiet machine: the shipped run took 697 s),
# 1200 steps (the unseen-voice numbers against steps are in benchmarks/README.md), exported with its sampling
# default (K = 4 DDIM steps, classifier-free guidance 1.25, no output filter) as the teacher; then its guidance is
# folded into one network row a step (`distill --steps 4`: half the cost a window, the same motion's measures) on the
# clip's training audio and 54 minutes of espeak-ng speech (benchmarks/speech_corpus.py; needs espeak-ng), two
# threads, ~17 min (the shipped run took 916 s); then that 4-step student's steps are halved (`distill --steps 2`,
# each step learns two of its teacher's, with the wrists' speed and acceleration weighted 8x; ~13 min, the shipped
# run took 572 s after 161 s of labelling), and the 2-step student's inference files go into the package.
ZEGGS ?= ../shared/data/zeggs_sample
default-model: $(VENV)/.serve-installed
	OMP_NUM_THREADS=1 $(BIN)/dimgestor train --data $(ZEGGS) --preset realtime --recipe streaming --out runs/default \
		--max-steps 1200 --window-s 5 --batch-size 8 --threads 1 --ckpt-every 400 --valid-every 400 --seed 0 \
		--valid-seconds 15 --no-augment --set frontend=speech --set lookahead_ms=300 --set down_kernel=41 \
		--cond-drop 0.15
	$(BIN)/dimgestor export --checkpoint runs/default --out runs/default_teacher --steps 4 --smooth 0 \
		--guidance 1.25
	$(BIN)/python benchmarks/speech_corpus.py --out runs/speech
	$(BIN)/dimgestor distill --checkpoint runs/default_teacher --data $(ZEGGS) --out runs/default_folded --steps 4 \
		--audio runs/speech --max-steps 1200 --valid-every 200 --ckpt-every 200 --threads 2
	$(BIN)/dimgestor distill --checkpoint runs/default_folded --data $(ZEGGS) --out runs/default_2step --steps 2 \
		--audio runs/speech --max-steps 1200 --valid-every 200 --ckpt-every 200 --threads 2 --vel-weight 8 \
		--acc-weight 8
	$(BIN)/dimgestor export --checkpoint runs/default_2step --out dimgestor/default_model --steps 2 --smooth 0

# The embedded live model (`--checkpoint live`, MODEL_CARD.md "The live model"): the default model's recipe with
# the realtime preset's own 150 ms of lookahead (downsampler kernel 31), so a frame needs audio up to 200 ms after
# its start instead of 350: what a live microphone wants. Same data, steps, dropout, sampling defaults and
# distillations (~19 min and ~16 min; the shipped runs took 1,037 s and 978 s).
live-model: $(VENV)/.serve-installed
	OMP_NUM_THREADS=1 $(BIN)/dimgestor train --data $(ZEGGS) --preset realtime --recipe streaming --out runs/live \
		--max-steps 1200 --window-s 5 --batch-size 8 --threads 1 --ckpt-every 400 --valid-every 400 --seed 0 \
		--valid-seconds 15 --no-augment --set frontend=speech --cond-drop 0.15
	$(BIN)/dimgestor export --checkpoint runs/live --out runs/live_teacher --steps 4 --smooth 0 --guidance 1.25
	$(BIN)/python benchmarks/speech_corpus.py --out runs/speech
	$(BIN)/dimgestor distill --checkpoint runs/live_teacher --data $(ZEGGS) --out runs/live_folded --steps 4 \
		--audio runs/speech --max-steps 1200 --valid-every 200 --ckpt-every 200 --threads 2
	$(BIN)/dimgestor distill --checkpoint runs/live_folded --data $(ZEGGS) --out runs/live_2step --steps 2 \
		--audio runs/speech --max-steps 1200 --valid-every 200 --ckpt-every 200 --threads 2 --vel-weight 8 \
		--acc-weight 8
	$(BIN)/dimgestor export --checkpoint runs/live_2step --out dimgestor/live_model --steps 2 --smooth 0
