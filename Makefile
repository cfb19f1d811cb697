# shadowlab: `make demo` and `make test` set up everything they need (venv, package, libLLVM; the tests also Chromium).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
LLVM_PKG ?= libllvm19
CHROMIUM_PKG ?= chromium

.PHONY: setup run-deps venv llvm browser engines demo test test-fast lint bench references docs clean

setup: venv llvm browser engines

# what running shadowlab needs (the tests also need the browser)
run-deps: venv llvm

venv: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	@touch $@

# Dr.Jit's LLVM backend needs libLLVM >= 16 (Mitsuba 3.9 kernels abort on 14/15).
llvm: venv
	@if $(PY) -c "import sys; from shadowlab.libllvm import find_libllvm; sys.exit(0 if find_libllvm() else 1)"; then \
		echo "libLLVM: $$($(PY) -c 'from shadowlab.libllvm import find_libllvm; print(find_libllvm())')"; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
		echo "installing $(LLVM_PKG) for Dr.Jit's LLVM backend"; \
		DEBIAN_FRONTEND=noninteractive apt-get install -y -q $(LLVM_PKG) >/dev/null 2>&1 || \
		{ apt-get update -q >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $(LLVM_PKG) >/dev/null; }; \
	else \
		echo "error: no libLLVM >= 16 found. Run: sudo apt-get install $(LLVM_PKG)" \
		     "(or set DRJIT_LIBLLVM_PATH to a libLLVM.so >= 16), then run make again." >&2; exit 3; \
	fi

# The report's browser test (tests/test_report_browser.py) loads a report in headless Chromium.
# Installed like libLLVM (apt-get as root); without root only a warning: `make demo` does not need it,
# and the test fails saying what to install.
browser:
	@if b=$$(command -v chromium || command -v chromium-browser || command -v google-chrome) || \
	    [ -n "$$SHADOWLAB_CHROMIUM" ]; then \
		echo "chromium: $${SHADOWLAB_CHROMIUM:-$$b}"; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
		echo "installing $(CHROMIUM_PKG) for the report's browser test"; \
		DEBIAN_FRONTEND=noninteractive apt-get install -y -q $(CHROMIUM_PKG) >/dev/null 2>&1 || \
		{ apt-get update -q >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $(CHROMIUM_PKG) >/dev/null; }; \
	else \
		echo "warning: no Chromium found; tests/test_report_browser.py needs it. Run: sudo apt-get install" \
		     "$(CHROMIUM_PKG) (or set SHADOWLAB_CHROMIUM to a Chromium binary)." >&2; \
	fi

# The engines (three.js, Babylon.js) and the Khronos glTF validator, pinned by package-lock.json.
engines: node_modules/.installed

node_modules/.installed: package.json package-lock.json
	@command -v npm >/dev/null || { echo "error: npm not found; the engine tests need Node.js >= 18 and npm." \
		"Run: sudo apt-get install nodejs npm, then make again." >&2; exit 3; }
	npm ci --no-audit --no-fund --loglevel=error
	@touch $@

demo: run-deps
	$(VENV)/bin/shadowlab demo --out reports/demo

test: setup lint
	$(PY) -m pytest -q

# ruff (configured in pyproject.toml) over the package and the tests
lint: venv
	$(VENV)/bin/ruff check shadowlab tests docs/conf.py

# While editing: the tests not marked slow (tests/conftest.py marks them from measured durations:
# SLOW_FILES, SLOW_TESTS), in about a minute on 2 cores. `make test` runs them all.
test-fast: setup
	$(PY) -m pytest -q -m "not slow"

bench: run-deps
	$(VENV)/bin/shadowlab bench --out reports/bench

# Re-render the committed ground truth of every built-in scene at CI resolution.
references: run-deps
	for s in $$($(VENV)/bin/shadowlab scenes --names); do \
		$(VENV)/bin/shadowlab reference $$s --force || exit $$?; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache docs/_build

# Regenerate the docs pages that come from scene files, technique declarations and bench run records,
# then build the site (docs/_build/html) with warnings as errors, as the tests do.
docs: venv
	$(PY) -m shadowlab.docs
	$(PY) -m sphinx -W --keep-going -q -b html docs docs/_build/html
	@echo "docs: docs/_build/html/index.html"
