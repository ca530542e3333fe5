# The two set-up commands of the README. Each creates .venv and installs into it when missing.
PY      ?= python3.11
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
OUT     ?= out/demo
JOBS    ?= 2

.PHONY: demo test test-slow bench checkpoints clean-venv

$(STAMP): setup.cfg constraints.txt
	@command -v $(PY) >/dev/null 2>&1 || { echo "need $(PY) on PATH (or set PY=python3)"; exit 2; }
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt torch==2.13.0
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/hrn-pyg demo --out $(OUT)

test: $(STAMP)
	$(BIN)/python -m pytest -n $(JOBS) tests

test-slow: $(STAMP)
	HRN_SLOW=1 $(BIN)/python -m pytest -n $(JOBS) tests

bench: $(STAMP)
	$(BIN)/python benchmarks/generate.py

# Remake every shipped checkpoint from data/recipes.toml into hrn_pyg/checkpoints (data/README.md).
# A rerun continues where a killed one stopped. Options pass through, e.g.
# make checkpoints CHECKPOINTS_ARGS="--only wedge --jobs 4 --device cuda"
CHECKPOINTS_ARGS ?=
checkpoints: $(STAMP)
	$(BIN)/hrn-pyg checkpoints --checkpoints-dir hrn_pyg/checkpoints $(CHECKPOINTS_ARGS)

clean-venv:
	rm -rf $(VENV)
