# The two commands of the README: `make test` and `make demo`. Both set up
# everything they need on a fresh machine (a .venv beside this file).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Process-wide defaults (MUJOCO_GL, OMP_WAIT_POLICY, ...) are set by `import tacsplat` (tacsplat/__init__.py).

.PHONY: test test-browser demo setup bench-step bench-compare bench-rasterizer bench-sim bench-quick bench-paper bench-touches bench-scaling bench-gpu gpu-prepare gpu-check clean

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

# tests/warm_kernels.py fills numba's cache beside the first tests, which mostly wait on device timeouts; two
# pytest workers (pytest-xdist), one per core of the 2-core machine the suite is sized for
test: $(STAMP)
	$(PY) -m ruff format --check --quiet . && $(PY) -m ruff check --quiet .
	$(PY) tests/warm_kernels.py >/dev/null 2>&1 & warm=$$!; \
	$(PY) -m pytest -m "not slow and not browser" -q -n 2; status=$$?; wait $$warm; exit $$status

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
	$(VENV)/bin/tacsplat bench gpu --steps 30000 --out bench-output/gpu

# The GPU check, in two steps (docs/gpu.md). Here, before a device call, `make gpu-prepare` writes .gpu/
# (git-ignored): the wheels the device's image lacks (its python3 is 3.12 with a CUDA torch) and the parity scene
# with its CPU runs. There, with .gpu carried, `make gpu-check` (no setup step: nothing can be installed from the
# network there) links this tree into GPU_SITE beside the wheels and runs `tacsplat bench gpu` from there
# (PYTHONSAFEPATH: not from this folder's tacsplat/, which lacks its subpackages); without CUDA it says so in one
# line and exits 0.
GPU_WHEELS := gsplat trimesh rtree embreex manifold3d plyfile pydantic pydantic-core annotated-types \
	typing-inspection typing-extensions mujoco-core PyOpenGL tyro docstring-parser typeguard shtab
GPU_GL_DEBS := libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2  # MuJoCo's EGL loader, which the image lacks
APT_AMD64 := -oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/apt-amd64-lists
GPU_PLATFORMS := --platform manylinux_2_17_x86_64 --platform manylinux_2_27_x86_64 \
	--platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64
GPU_PYTHON ?= python3
GPU_SITE ?= /tmp/tacsplat-gpu-site
GPU_PARITY ?= .gpu/parity
GPU_WHEEL_DIR ?= .gpu/wheels
GPU_OUT ?= $(if $(OUT),$(OUT),bench-output/gpu)
GPU_ARGS ?=
SUBPACKAGES := acquisition datasets drivers reconstruction sim

gpu-prepare: $(STAMP)
	rm -rf $(GPU_WHEEL_DIR) && mkdir -p $(GPU_WHEEL_DIR)
	$(PY) -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
		$(GPU_PLATFORMS) -d $(GPU_WHEEL_DIR) $$($(PY) -c "import importlib.metadata as m, sys; \
		print(' '.join(n + '==' + m.version(n) for n in sys.argv[1:]))" $(GPU_WHEELS))
	rm -rf .gpu/gl /tmp/apt-amd64-lists && mkdir -p .gpu/gl /tmp/apt-amd64-lists/partial
	apt-get $(APT_AMD64) update -qq && cd .gpu/gl && apt-get $(APT_AMD64) download $(GPU_GL_DEBS)
	$(VENV)/bin/tacsplat bench gpu --prepare $(GPU_PARITY)

gpu-check:
	@if $(GPU_PYTHON) -c "import torch, sys; sys.exit(not torch.cuda.is_available())" 2>/dev/null; then cuda=yes; \
	elif [ -z "$(findstring --device cpu,$(GPU_ARGS))" ]; then \
		echo "gpu-check: skipped: $(GPU_PYTHON) here has no CUDA device (or no torch); nothing was measured"; exit 0; \
	fi; \
	test -f $(GPU_PARITY)/cpu.json || { echo "gpu-check: no $(GPU_PARITY)/cpu.json: run make gpu-prepare here \
	first and carry .gpu"; exit 1; }; \
	set -e; rm -rf $(GPU_SITE); mkdir -p $(GPU_SITE)/tacsplat; \
	if [ "$$cuda" = yes ] && ! ldconfig -p | grep -q libEGL.so.1 && ls .gpu/gl/*.deb >/dev/null 2>&1; then \
		for f in .gpu/gl/*.deb; do dpkg -x $$f /; done; ldconfig; fi; \
	egl=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json; \
	if [ -f $$egl ]; then export __EGL_VENDOR_LIBRARY_FILENAMES=$${__EGL_VENDOR_LIBRARY_FILENAMES:-$$egl}; fi; \
	if ls $(GPU_WHEEL_DIR)/*.whl >/dev/null 2>&1; then $(GPU_PYTHON) -m pip install --quiet --no-index \
		--no-deps --no-compile --target $(GPU_SITE) $(GPU_WHEEL_DIR)/*.whl; fi; \
	ln -s $(CURDIR)/tacsplat/* $(GPU_SITE)/tacsplat/; \
	for p in $(SUBPACKAGES); do ln -s $(CURDIR)/$$p $(GPU_SITE)/tacsplat/$$p; done; \
	PYTHONPATH=$(GPU_SITE) PYTHONSAFEPATH=1 MUJOCO_GL=egl $(GPU_PYTHON) -m tacsplat.cli bench gpu --out $(GPU_OUT) --work $(GPU_SITE)-work \
		--parity $(GPU_PARITY) $(GPU_ARGS)

clean:
	rm -rf $(VENV) demo-output bench-output .pytest_cache
