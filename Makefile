# Two user targets: `make run` (the default scene, headless) and `make test` (the test suite).
# Both depend on `install`, which is idempotent: a stamp in .venv skips it the second time.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export PYTHONUNBUFFERED := 1

.PHONY: install run test
install: $(STAMP)

$(STAMP): requirements.txt Makefile
	dpkg -s libsuitesparse-dev >/dev/null 2>&1 || (apt-get update && apt-get install -y libsuitesparse-dev)
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q -r requirements.txt
	$(PY) -m pip install -q --no-build-isolation "scikit-sparse==0.4.16"
	touch $(STAMP)

run: install
	$(PY) -m soft_tissue_sim.ros.demo --scene default.yaml --steps 300

test: install
	$(PY) -m pytest -q test
