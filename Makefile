# The README's commands. Each creates .venv and installs the project first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
INSTALLED := $(VENV)/.installed
NODE_INSTALLED := node_modules/.installed

.PHONY: demo test lint typecheck docs pytest bench clean

$(BIN)/python:
	$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11) and "srvwire needs Python 3.11 or newer")'
	$(PYTHON) -m venv $(VENV)

$(INSTALLED): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $@

# wscat, which tests/test_wscat.py drives, comes from npm (package.json, package-lock.json).
$(NODE_INSTALLED): package.json package-lock.json
	@command -v npm >/dev/null 2>&1 || { echo 'make test needs Node.js and npm: tests/test_wscat.py runs wscat, installed from npm' >&2; exit 1; }
	npm ci --no-audit --no-fund --loglevel=error
	touch $@

# Chromium, in which tests/test_docs_site.py opens the built docs site: the Debian package,
# installed here when it is missing and make runs as root (as on CI).
.PHONY: chromium
chromium:
	@command -v chromium >/dev/null 2>&1 || [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1 \
		|| { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; }
	@command -v chromium >/dev/null 2>&1 || { echo 'make test needs Chromium: tests/test_docs_site.py opens the docs site in it; install the Debian package: apt-get install chromium' >&2; exit 1; }

demo: $(INSTALLED)
	@$(BIN)/python examples/demo.py

lint: $(INSTALLED)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

typecheck: $(INSTALLED)
	$(BIN)/mypy --strict src examples

docs: $(INSTALLED)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet --site-dir site

# The suite on every core (pytest-xdist); PYTEST_WORKERS=0 runs it in this one process. Each
# file runs on one worker (--dist loadfile), so a module's fixtures (the docs site, the wheel,
# the harness's quick run) are made once; files are handed out in name order, not most tests
# first, which would start the benchmark harness's few long tests last. Not in pytest's
# addopts: `pytest tests/test_x.py` starts no workers.
PYTEST_WORKERS ?= auto
pytest: $(INSTALLED) $(NODE_INSTALLED) chromium
	$(BIN)/pytest -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder

test: lint typecheck docs pytest

# Not part of `make test`: several minutes of srvwire against a raw-websockets baseline,
# asyncio then uvloop (benchmarks/README.md). BENCH_ARGS=--quick for a smoke run.
# Each transport against its own raw floor, and the native one against raw websockets too;
# srvwire against the JSON-RPC peer (aiohttp-json-rpc + jsonrpc-websocket).
BENCH_COMPARE ?= --compare baseline,srvwire --compare picows,srvwire-picows \
	--compare baseline,srvwire-picows --compare peer,srvwire
bench: $(INSTALLED)
	$(BIN)/python -m pip install --quiet -e '.[dev,bench]'
	$(BIN)/python benchmarks/run.py --loop asyncio,uvloop $(BENCH_COMPARE) $(BENCH_ARGS)

clean:
	rm -rf $(VENV) site build dist .mypy_cache .ruff_cache .pytest_cache
