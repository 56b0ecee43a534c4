# The two commands: `make demo` (main job on the bundled fixture) and `make test` (the test suite).
# Both create .venv on first use: torch first (pinned; on the project's machines 2.13.0 is a local
# CPU wheel), then the project with its dev extra.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.couch-installed

.PHONY: test demo lint bench fixtures system-deps clean

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

# Two worker processes (pytest-xdist) by default, one per core of the 2-core machines we target;
# each test file runs whole on one worker (tests/conftest.py). `make test TEST_WORKERS=0` runs
# the suite in one process.
TEST_WORKERS ?= 2

test: $(STAMP)
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --no-loadscope-reorder

# The main job on the bundled fixture session: couch-process (calibration, chair registration,
# sync, body fits, contacts) into out/fixture_processed/, its summary, and where the report is.
# A second run resumes from the stage cache in out/fixture_processed/cache/.
demo: $(STAMP)
	$(BIN)/couch-process fixtures/sessions/sim_fixture -o out/fixture_processed
	$(BIN)/couch-inspect out/fixture_processed/processed.h5
	@echo "QA report: out/fixture_processed/report/index.html"

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python -m couch.tools.bench.body

clean:
	rm -rf $(VENV) out .pytest_cache

# The committed fixture session (fixtures/sessions/sim_fixture): regenerate with `make fixtures`.
# 6 s (the IMU sync needs >= 4 s of overlap), 4 cameras at 5 fps, 320x288 depth
# (NFOV_2X2BINNED), 3 ChArUco poses, seed 4.
FIXTURE := fixtures/sessions/sim_fixture
fixtures: $(STAMP)
	rm -rf $(FIXTURE)
	$(BIN)/couch-simulate $(FIXTURE) --duration 6 --fps 5 --cameras 4 \
	  --depth-mode NFOV_2X2BINNED --charuco-poses 3 --jpeg-quality 80 --masks --seed 4 --quiet
