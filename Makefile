# The whole set-up is two commands: `make run` and `make test` (see README.md).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
VENDOR := static/vendor

.PHONY: install run test lint typecheck pytest clean

install: $(STAMP)

# Everything pinned: Python packages from the lock files, front-end libraries from package-lock.json.
$(STAMP): requirements.lock requirements-robots.lock requirements-dev.lock pyproject.toml package.json package-lock.json
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -r requirements-dev.lock
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps -e .
	npm ci --ignore-scripts --no-audit --no-fund --loglevel=error
	mkdir -p $(VENDOR)
	cp node_modules/htmx.org/dist/htmx.min.js node_modules/htmx-ext-sse/dist/sse.min.js \
	   node_modules/plotly.js-cartesian-dist-min/plotly-cartesian.min.js \
	   node_modules/swagger-ui-dist/swagger-ui-bundle.js node_modules/swagger-ui-dist/swagger-ui.css $(VENDOR)/
	mkdir -p $(VENDOR)/three
	cp node_modules/three/build/three.module.js node_modules/three/build/three.core.js \
	   node_modules/three/LICENSE $(VENDOR)/three/
	@touch $(STAMP)

run: install
	$(BIN)/trustlab init
	$(BIN)/trustlab serve

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

typecheck: install
	$(BIN)/mypy

# Two parts: everything else spread over the machine's cores (pytest-xdist, worksteal), then the
# tests marked `exclusive`, which restart the shared PostgreSQL and so must run alone.
# Bytecode is written even where the environment says PYTHONDONTWRITEBYTECODE: every xdist worker
# and every server a test starts would otherwise compile the app and the test modules afresh
# (about 7 s of CPU per worker's collection alone).
pytest: install
	PYTHONDONTWRITEBYTECODE= $(BIN)/pytest -n auto --dist worksteal -m "not exclusive"
	PYTHONDONTWRITEBYTECODE= $(BIN)/pytest -m exclusive

test: lint typecheck pytest

clean:
	rm -rf $(VENV) node_modules $(VENDOR)
