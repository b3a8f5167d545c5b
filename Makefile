# The two commands of the README: `make test` and `make demo`. Both set up
# everything they need on a fresh machine (a .venv beside this file).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Process-wide defaults (MUJOCO_GL, OMP_WAIT_POLICY, ...) are set by `import tacsplat` (tacsplat/__init__.py).

.PHONY: test test-browser demo setup bench-step bench-compare bench-rasterizer bench-sim bench-quick bench-paper bench-touches bench-scaling bench-gpu clean

setup: $(STAMP)

# torch first and pinned: 2.13.0 is the CPU wheel on these machines; letting
# pip choose pulls a multi-GB CUDA build. Elsewhere choose the build, e.g.
#   make test TORCH_INDEX=https://download.pytorch.org/whl/cpu   (CPU only)
TORCH ?= torch==2.13.0
TORCH_INDEX ?=
# every extra (the base install alone, the scene format, reconstruction and the CLI: pip install -e .)
EXTRAS ?= dev,sim,hardware,viewer,cluster
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) '$(TORCH)'
	$(PY) -m pip install --quiet -e '.[$(EXTRAS)]'
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m ruff format --check --quiet . && $(PY) -m ruff check --quiet .
	$(PY) -m pytest -m "not slow and not browser" -q

# the viewer in headless Chromium (Debian's package, installed when missing)
SUDO := $(if $(filter 0,$(shell id -u)),,sudo)
test-browser: $(STAMP)
	command -v chromium >/dev/null || { $(SUDO) apt-get update && $(SUDO) apt-get install -y --no-install-recommends chromium; }
	$(PY) -m pytest -m browser -q tests/apps/test_viewer_browser.py

demo: $(STAMP)
	$(VENV)/bin/tacsplat demo --out demo-output

bench-rasterizer: $(STAMP)
	$(VENV)/bin/tacsplat bench rasterizer --json bench-output/rasterizer.json

# where a training step's time goes (table, step.png, step.json); compare two JSON results:
#   make bench-compare A=old/step.json B=bench-output/step/step.json
bench-step: $(STAMP)
	$(VENV)/bin/tacsplat bench step --out bench-output/step

bench-compare: $(STAMP)
	$(VENV)/bin/tacsplat bench compare $(A) $(B)

bench-sim: $(STAMP)
	$(VENV)/bin/tacsplat bench sim --out bench-output/sim

bench-quick: $(STAMP)
	$(PY) -m pytest -m slow -q -k quick

bench-paper: $(STAMP)
	$(VENV)/bin/tacsplat bench paper --objects all --out bench-output/paper

bench-touches: $(STAMP)
	$(VENV)/bin/tacsplat bench touches --out bench-output/touches

bench-scaling: $(STAMP)
	$(VENV)/bin/tacsplat bench scaling --out bench-output/scaling

bench-gpu: $(STAMP)
	$(VENV)/bin/tacsplat bench gpu --out bench-output/gpu

clean:
	rm -rf $(VENV) demo-output bench-output .pytest_cache
