# The two commands: `make demo` (main job on the bundled fixture) and `make test` (the test suite).
# Both create .venv on first use: torch first (pinned; on the project's machines 2.13.0 is a local
# CPU wheel), then the project with its dev extra.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.couch-installed

.PHONY: test demo lint bench system-deps clean

$(STAMP): pyproject.toml
	@$(MAKE) --no-print-directory system-deps
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

# open3d's wheel links libusb-1.0 (Debian/Ubuntu package libusb-1.0-0); `import open3d` fails
# without it. Installed here when we are root with apt-get; otherwise we stop and say what to do.
system-deps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing libusb-1.0-0 (needed by open3d)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0; \
	  else \
	    echo "couch needs the system library libusb-1.0 for open3d."; \
	    echo "Install it first, e.g.: sudo apt-get install libusb-1.0-0   (Fedora: libusb1)"; \
	    exit 1; \
	  fi; \
	fi

test: $(STAMP)
	$(BIN)/python -m pytest

demo: $(STAMP)
	$(BIN)/couch-demo -o out/demo_sitting.png

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python -m couch.tools.bench.body

clean:
	rm -rf $(VENV) out .pytest_cache
