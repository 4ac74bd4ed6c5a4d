# Two commands: `make run` (main job) and `make test` (test suite). Both create .venv if missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)

.PHONY: install run test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e ".[test,mjx]"
	rm -f $(VENV)/.installed-*; touch $(STAMP)

install: $(STAMP)

run: install
	$(BIN)/jaxnc run mecanum --seeds 256 --set case=all --out results/mecanum

test: install
	$(BIN)/python -m pytest -q -n 2 -m "not slow" --durations=25

bench: install
	$(BIN)/python benchmarks/bench_mecanum.py

clean:
	rm -rf $(VENV) results build *.egg-info
