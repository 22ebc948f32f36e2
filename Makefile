# Two commands on a fresh machine: `make demo` and `make test` (each creates .venv first).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-all bench install clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,ipopt,cosim,study,viewer]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/msagv demo

# the web-viewer test screenshots Rerun's viewer in headless Chromium (Debian's package);
# installed here when missing and possible (root with apt-get), else that test skips
CHROMIUM_CHECK = command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && { apt-get install -y -q chromium >/dev/null 2>&1 || { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q chromium >/dev/null 2>&1; }; }; } || echo "chromium not installed: the web-viewer screenshot test will skip"

test: $(STAMP)
	@$(CHROMIUM_CHECK)
	$(BIN)/python -m pytest -q

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -m ''

bench: $(STAMP)
	$(BIN)/msagv bench

clean:
	rm -rf $(VENV) build *.egg-info
