# Two commands: `make demo` and `make test`. Both create .venv when missing and
# install the project into it; the install is skipped when pyproject.toml is unchanged.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# JavaScript for the tests (Khronos glTF validator) and the viewer's three.js, pinned in
# package-lock.json; npm ci reinstalls them when the lock file changes.
NODE_STAMP := node_modules/.installed

.PHONY: demo test bench install lint clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
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

clean:
	rm -rf $(VENV) runs build *.egg-info node_modules
