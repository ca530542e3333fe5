# The two set-up commands of the README. Each creates .venv and installs into it when missing.
PY      ?= python3.11
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
OUT     ?= runs/demo
JOBS    ?= 2

.PHONY: demo test test-slow bench checkpoints mutation clean-venv

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
	$(BIN)/python -m benchmarks.generate

# Remake every shipped checkpoint from data/recipes.toml into hrn_pyg/checkpoints (data/README.md;
# experiments/recipe, a maintainer tool outside the wheel).
# A rerun continues where a killed one stopped. Options pass through, e.g.
# make checkpoints CHECKPOINTS_ARGS="--only wedge --jobs 4 --device cuda"
CHECKPOINTS_ARGS ?=
checkpoints: $(STAMP)
	$(BIN)/python -m experiments.recipe --checkpoints-dir hrn_pyg/checkpoints $(CHECKPOINTS_ARGS)

# Mutation testing (mutmut, the optional `mutation` extra; not part of `make test` or CI): stats,
# stability, the scene file's draws and expressions in turn, one process each, against their own
# test files, in a copy under out/mutation/ (tests/mutation.py). MUTATE="stats stability" runs some.
MUTATE ?=
mutation: $(STAMP)
	$(BIN)/python -c "import mutmut" 2>/dev/null || $(BIN)/python -m pip install -q -c constraints.txt -e '.[mutation]'
	$(BIN)/python tests/mutation.py $(MUTATE)

clean-venv:
	rm -rf $(VENV)
