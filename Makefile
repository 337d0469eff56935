# coopmap — two-command set-up: `make demo` and `make test` each build what they need.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.coopmap-installed
# Shared libraries that Open3D loads at import time, and the Debian packages that provide them.
SYSLIBS := libusb-1.0.so.0:libusb-1.0-0 libgomp.so.1:libgomp1

.PHONY: demo test lint typecheck bench clean syslibs

demo: $(STAMP)
	$(BIN)/coopmap demo

# The README's test command: everything CI runs (lint, types, the test suite, one pytest
# worker per core, at most 4).
test: lint typecheck
	$(BIN)/python -m pytest -q --numprocesses auto --maxprocesses 4

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

typecheck: $(STAMP)
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/coopmap bench fusion
	$(BIN)/coopmap bench search
	$(BIN)/coopmap bench graph

syslibs:
	@missing=""; \
	for pair in $(SYSLIBS); do \
	  lib=$${pair%%:*}; pkg=$${pair##*:}; \
	  /sbin/ldconfig -p 2>/dev/null | grep -q "$$lib" || missing="$$missing $$pkg"; \
	done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "coopmap: installing system libraries:$$missing"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing >/dev/null || exit 1; \
	  else \
	    echo "coopmap: Open3D needs system libraries that are missing:$$missing" >&2; \
	    echo "coopmap: install them with:  sudo apt-get install -y$$missing" >&2; \
	    exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' || \
	  { echo "coopmap: needs Python >= 3.11 (found: $$($(PYTHON) --version 2>&1)); set PYTHON=python3.11 or newer" >&2; exit 1; }
	@$(MAKE) --no-print-directory syslibs
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache .mypy_cache
