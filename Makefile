# Two commands on a fresh machine: `make demo` and `make test` (each creates .venv first).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-all bench install clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,ipopt,cosim,study,viewer,foxglove]'
	$(BIN)/python -m pip install -q -e '.[ros2]' || echo "ROS 2 wheels not installed: the ROS 2 tests will skip"
	touch $(STAMP)

# acados (--solver acados) for the tests and benchmarks, never for the demo. The registry's
# comma-deps-acados vendors a slim casadi 3.6.7 (no IPOPT) under the same import name as the
# ipopt extra's, so it is not installed as an extra: it goes into its own directory, where
# controller/acados_rti.py finds it, and its casadi is never imported. Optional: without
# it the acados tests skip.
ACADOS := $(VENV)/acados
ACADOS_STAMP := $(ACADOS)/.installed

$(ACADOS_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q --no-deps --upgrade --target $(ACADOS) comma-deps-acados && touch $(ACADOS_STAMP) || echo "comma-deps-acados not installed: the acados tests will skip"

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/msagv demo

# the web-viewer test screenshots Rerun's viewer in headless Chromium (Debian's package);
# installed here when missing and possible (root with apt-get), else that test skips
CHROMIUM_CHECK = command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && { apt-get install -y -q chromium >/dev/null 2>&1 || { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q chromium >/dev/null 2>&1; }; }; } || echo "chromium not installed: the web-viewer screenshot test will skip"

# the official Foxglove client (npm @foxglove/ws-protocol) that tests/test_foxglove.py runs in
# Node: Debian's nodejs and npm installed when missing and possible (root with apt-get), then
# the client's packages as tests/node/package-lock.json pins them (npm ci into
# tests/node/node_modules, which git ignores). Without npm that test skips; a failed npm ci
# fails here.
NODE_CHECK = command -v npm >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && { apt-get install -y -q nodejs npm >/dev/null 2>&1 || { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q nodejs npm >/dev/null 2>&1; }; }; } || echo "npm not installed: the Foxglove npm-client test will skip"
NPM_STAMP := tests/node/node_modules/.package-lock.json

$(NPM_STAMP): tests/node/package.json tests/node/package-lock.json
	@$(NODE_CHECK)
	@if command -v npm >/dev/null 2>&1; then cd tests/node && npm ci --no-audit --no-fund --loglevel=error; fi

test: $(STAMP) $(ACADOS_STAMP) $(NPM_STAMP)
	@$(CHROMIUM_CHECK)
	$(BIN)/python -m pytest -q -n 2 --dist loadscope --durations=30

test-all: $(STAMP) $(ACADOS_STAMP) $(NPM_STAMP)
	$(BIN)/python -m pytest -q -m ''

bench: $(STAMP) $(ACADOS_STAMP)
	$(BIN)/msagv bench

clean:
	rm -rf $(VENV) build *.egg-info tests/node/node_modules
