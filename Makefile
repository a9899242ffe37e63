# Two user targets: `make run` (the default scene, headless) and `make test` (the test suite).
# Both depend on `install`, which is idempotent: a stamp in .venv skips it the second time.
# `install` ends with the package itself installed into .venv (editable: the checkout's code,
# config/ and meshes/), so `.venv/bin/python -m soft_tissue_sim.ros`, `from soft_tissue_sim
# import load_scene` and `.venv/bin/sim_node` work from any directory.
# `make install-cuda` adds the GPU libraries (requirements-cuda.txt; a CUDA 13 machine).
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export PYTHONUNBUFFERED := 1

.PHONY: install install-cuda run test
install: $(STAMP)

$(STAMP): requirements.txt setup.py Makefile
	dpkg -s libsuitesparse-dev >/dev/null 2>&1 || (apt-get update && apt-get install -y libsuitesparse-dev)
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q -r requirements.txt
	$(PY) -m pip install -q --no-build-isolation "scikit-sparse==0.4.16"
	$(PY) -m pip install -q --no-build-isolation --no-deps -e .
	touch $(STAMP)

install-cuda: install
	$(PY) -m pip install -q -r requirements-cuda.txt

run: install
	$(PY) -m soft_tissue_sim.ros.demo --scene default.yaml --steps 300

test: install
	$(PY) -m pytest -q test
