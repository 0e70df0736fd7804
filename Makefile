# The two commands a newcomer needs: `make demo` and `make test`. Each sets itself up first
# (scripts/bootstrap.sh: Debian packages and .venv/), idempotently.
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: setup demo test check lint types protocol-check firmware-test firmware-test-one pytest pytest-fast clean

setup:
	@scripts/bootstrap.sh

# The daemon drives the simulated phantom (the firmware image in simavr) through the BPH growth scene.
demo: setup
	$(MAKE) -C firmware
	$(PY) -m phantom.cli.demo --scene host/scenes/bph_growth.toml --time-scale 3 --out out

test: setup lint types protocol-check firmware-test pytest

# The contributor's fast loop, under a minute: lint, types, the protocol check and the tests that need no
# simulator (pytest -m "not sim and not slow"; mark a test that runs simavr with @pytest.mark.sim).
check: setup lint types protocol-check pytest-fast

lint:
	$(VENV)/bin/ruff check .

# mypy: strict on phantom.protocol, and phantom.host (settings in pyproject.toml). mypy cannot follow the
# editable install's import hook, so the package's folders are mapped into one tree under .cache/ first.
MYPY_TREE := .cache/mypy-src/phantom
types:
	@mkdir -p $(MYPY_TREE)
	@for f in __init__.py __main__.py cli; do ln -sfn ../../../phantom/$$f $(MYPY_TREE)/$$f; done
	@for d in protocol model scan host hil; do ln -sfn ../../../$$d $(MYPY_TREE)/$$d; done
	$(VENV)/bin/mypy -p phantom.protocol -p phantom.host

# The generated protocol files (messages.py, protocol_generated.h) must match protocol/spec.toml.
protocol-check:
	$(PY) -m phantom.protocol.generate --check

# The firmware core's native unit tests, the C++ golden-vector test and a bounded libFuzzer run.
firmware-test:
	$(MAKE) -C firmware test PYTHON=$(abspath $(PY))

pytest-fast:
	$(PY) -m pytest -q -m "not sim and not slow"

pytest:
	$(PY) -m pytest -q

clean:
	rm -rf firmware/build hil/harness/build .pytest_cache .ruff_cache
