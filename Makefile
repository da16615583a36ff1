# mabdi: the two set-up commands of the README.
#   make run    install mabdi into .venv (what running needs) and run the MABDI loop on the table scene (SCENE=...)
#   make test   install the test extras too (pytest, Open3D for the TSDF peer, Ray, Rerun, Warp) and run the tests
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
SCENE ?= scenes/table.toml
# Test processes (pytest-xdist, a file's tests together): one per core, at most 4 (each full run holds 1-3 GB).
TEST_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || echo 2); [ "$$n" -gt 4 ] && n=4; echo $$n)

.PHONY: run test install install-test bench clean system-packages

# The system libraries (Mesa EGL/OSMesa, libusb): installed with apt-get as root on Debian, else a stop
# before anything else, naming the command to run.
system-packages:
	@bash tools/system-packages.sh

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# What running needs.
$(VENV)/.installed: pyproject.toml | $(VENV)/bin/python
	$(BIN)/python -m pip install --quiet -e .
	touch $@

# What the tests need on top: test tools, the comparison peer (Open3D), sweeps (Ray), live viewing (Rerun),
# the GPU path's kernels (Warp, run on the CPU by the tests).
$(VENV)/.installed-test: pyproject.toml $(VENV)/.installed
	$(BIN)/python -m pip install --quiet -e ".[test,compare,sweep,rerun,gpu]"
	touch $@

install: $(VENV)/.installed

install-test: $(VENV)/.installed-test

run: system-packages install
	$(BIN)/mabdi run $(SCENE)

test: system-packages install-test
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile

bench: system-packages install-test
	$(BIN)/python benchmarks/bench_depth_image.py

clean:
	rm -rf $(VENV) runs .pytest_cache
