# DrivingScene: `make run` (set up, then the viewer on the demo scene) and `make test`.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# A CPU build of torch (installed from local disk on our machines); override for a CUDA build.
TORCH_SPEC ?= torch==2.13.0
STAMP := $(VENV)/.installed
OUT ?= out

.PHONY: setup run test bench clean-venv

setup: $(STAMP)

$(STAMP): pyproject.toml .ci/install-system-deps.sh
	./.ci/install-system-deps.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip 2>/dev/null || true
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

run: setup
	$(VENV)/bin/drivingscene info assets/demo_scene.npz

test: setup
	$(PY) -m pytest -q -p no:cacheprovider

clean-venv:
	rm -rf $(VENV)
