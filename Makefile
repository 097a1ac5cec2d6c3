# batchpose: `make demo` and `make test` do all set-up themselves on a fresh Debian machine.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.batchpose-installed
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
export PYOPENGL_PLATFORM ?= osmesa

.PHONY: setup system-packages demo test lint clean-demo

setup: system-packages $(STAMP)

# Headless GL for pyrender (OSMesa by default; EGL works too).
system-packages:
	@if ! dpkg -s $(APT_PACKAGES) >/dev/null 2>&1; then \
		echo "Installing system packages: $(APT_PACKAGES)"; \
		$(SUDO) apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends $(APT_PACKAGES); \
	fi

# pyrender 0.1.45 pins PyOpenGL 3.1.0, whose OSMesa binding is broken; 3.1.10 must come in a second
# pip command (SPEC.md §1). pip then warns about the pin; that is expected.
$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	$(PY) -m pip install -q 'PyOpenGL==3.1.10' 2>&1 | grep -v "incompatible" || true
	touch $(STAMP)

demo: setup
	$(VENV)/bin/batchpose run pipelines/gnc_pose.yaml --manifest data_manifest/demo.yaml --out runs/demo
	@echo
	@echo "Output MCAP (open in Foxglove, see docs/foxglove.md): $(CURDIR)/runs/demo/poses.mcap"
	@echo "HTML report:                                          $(CURDIR)/runs/demo/report/index.html"
	@echo "BOP results:                                          $(CURDIR)/runs/demo/poses.csv"

test: setup
	$(PY) -m pytest -q

lint: setup
	$(VENV)/bin/ruff check batchpose tests benchmarks
