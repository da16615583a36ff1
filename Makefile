# mabdi: the two set-up commands of the README.
#   make run    install into .venv and run the MABDI loop on the table scene (SCENE=...)
#   make test   install into .venv (with the test extras) and run the tests
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
SCENE ?= scenes/table.toml

.PHONY: run test install bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,compare,sweep,rerun]"
	touch $@

install: $(VENV)/.installed

run: install
	$(BIN)/mabdi run $(SCENE)

test: install
	$(BIN)/python -m pytest

bench: install
	$(BIN)/python benchmarks/bench_depth_image.py

clean:
	rm -rf $(VENV) runs .pytest_cache
