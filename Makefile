# Two commands: `make demo` and `make test`. Both create .venv when missing and
# install the project into it; the install is skipped when pyproject.toml is unchanged.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# JavaScript for the tests (Khronos glTF validator) and the viewer's three.js, pinned in
# package-lock.json; npm ci reinstalls them when the lock file changes.
NODE_STAMP := node_modules/.installed

.PHONY: demo test bench fuzz install lint clean

# Coverage-guided fuzzing of the wire decoder (tests/fuzz_protocol.py); `make test` runs 12 s of it.
FUZZ_SECONDS ?= 600

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# setup.py and the C sources: the editable install compiles the optional C fast paths
# (setup.py's list) in place
C_SOURCES := $(wildcard protocol/*.c sumo_side/*.c physics_side/*.c physics_side/policies/*.c)
$(STAMP): pyproject.toml setup.py $(C_SOURCES) $(wildcard include/*.h physics_side/*.h) | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[all,test]'
	touch $(STAMP)

$(NODE_STAMP): package.json package-lock.json
	npm ci --no-audit --no-fund --ignore-scripts --loglevel=error
	touch $(NODE_STAMP)

install: $(STAMP) $(NODE_STAMP)

lint: $(STAMP)
	$(BIN)/lint-imports

demo: $(STAMP)
	$(BIN)/sumoco demo --config configs/demo.toml --out runs/demo

test: $(STAMP) $(NODE_STAMP)
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/sumoco bench sumo --json
	$(BIN)/sumoco bench physics --json

fuzz: $(STAMP)
	$(BIN)/python tests/fuzz_protocol.py --seconds $(FUZZ_SECONDS) --corpus build/fuzz-corpus

clean:
	rm -rf $(VENV) runs build *.egg-info node_modules $(C_SOURCES:.c=*.so)
