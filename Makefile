# batchpose: `make demo` and `make test` do all set-up themselves on a fresh Debian machine.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.batchpose-installed
# Exact versions (with hashes) for Python 3.11 on Linux x86_64, made from pyproject.toml by `make lock`.
LOCK := requirements.lock
LOCK_OVERRIDES := requirements-overrides.txt
# uv is only the lock tool: `make lock` puts it in $(VENV); it is no dependency of batchpose.
UV_VERSION ?= 0.13.9
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
export PYOPENGL_PLATFORM ?= osmesa

.PHONY: setup system-packages lock lock-upgrade demo test lint clean-demo

setup: system-packages $(STAMP)

# Headless GL for pyrender (OSMesa by default; EGL works too).
system-packages:
	@if ! dpkg -s $(APT_PACKAGES) >/dev/null 2>&1; then \
		echo "Installing system packages: $(APT_PACKAGES)"; \
		$(SUDO) apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends $(APT_PACKAGES); \
	fi

# Installs the lock as it is (--no-deps), then batchpose itself without its dependencies: pyrender 0.1.45
# pins PyOpenGL 3.1.0, whose OSMesa binding is broken, and the lock overrides it with 3.1.10 (SPEC.md §1;
# `pip check` reports that pin, as expected). Re-installs when the lock or pyproject.toml changes.
$(STAMP): pyproject.toml $(LOCK)
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q --no-deps -r $(LOCK)
	$(PY) -m pip install -q --no-deps -e .
	touch $(STAMP)

# Re-resolves the lock from pyproject.toml (with the dev extra and $(LOCK_OVERRIDES)), keeping every
# version already pinned that still fits; `make lock-upgrade` moves everything to the newest allowed.
# Then `make setup` installs it.
lock:
	@[ -x $(PY) ] || python3 -m venv $(VENV)
	@$(PY) -m pip install -q 'uv==$(UV_VERSION)'
	$(VENV)/bin/uv pip compile pyproject.toml --extra dev --override $(LOCK_OVERRIDES) \
		--python-version 3.11 --python-platform x86_64-manylinux_2_28 --generate-hashes \
		--custom-compile-command 'make lock' --quiet $(UV_ARGS) -o $(LOCK)

lock-upgrade:
	$(MAKE) lock UV_ARGS=--upgrade

demo: setup
	$(VENV)/bin/batchpose run --manifest data_manifest/demo.yaml --out runs/demo
	@echo
	@echo "Output MCAP (open in Foxglove, see docs/foxglove.md): $(CURDIR)/runs/demo/poses.mcap"
	@echo "HTML report:                                          $(CURDIR)/runs/demo/report/index.html"
	@echo "BOP results:                                          $(CURDIR)/runs/demo/poses.csv"

test: setup
	$(PY) -m pytest -q --durations=15  # the slowest tests: CI must stay near 15 minutes

lint: setup
	$(VENV)/bin/ruff check batchpose tests benchmarks
	$(VENV)/bin/ruff format --check batchpose tests benchmarks
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports