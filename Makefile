# The two set-up commands of the README: `make demo` and `make test`.
# Each creates or updates .venv itself (Python >= 3.11; PyPI and Debian packages only).

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
PYTEST_ARGS ?=
DEMO_MISSION ?= patrol
DEMO_PORT ?= 8080

.PHONY: demo test bench venv system-deps clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "Python >= 3.11 is required")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

# Debian tools the tests use for real (not mocks): systemd-analyze verifies the unit file,
# headless chromium drives the dashboard page, shellcheck reads the install script.
system-deps:
	@command -v systemd-analyze >/dev/null 2>&1 && command -v chromium >/dev/null 2>&1 \
	  && command -v shellcheck >/dev/null 2>&1 || { \
	  echo "installing Debian packages: systemd (for systemd-analyze), chromium (for the dashboard tests), shellcheck"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq systemd chromium shellcheck >/dev/null; }

# The simulated vehicle flying a mission, with the live dashboard (it prints the URL).
demo: $(STAMP)
	$(BIN)/companion sitl --mission $(DEMO_MISSION) --dashboard $(DEMO_PORT)

test: $(STAMP) system-deps
	$(BIN)/python -m pytest $(PYTEST_ARGS)

bench: $(STAMP)
	$(BIN)/companion bench

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
