# The two commands a newcomer needs: `make demo` and `make test`. Each sets itself up first
# (scripts/bootstrap.sh: Debian packages and .venv/), idempotently.
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: setup demo test lint protocol-check firmware-test pytest clean

setup:
	@scripts/bootstrap.sh

# The daemon drives the simulated phantom (the firmware image in simavr) through the BPH growth scene.
demo: setup
	$(MAKE) -C firmware
	$(PY) -m phantom.host.demo --scene host/scenes/bph_growth.toml --time-scale 3 --out out

test: setup lint protocol-check firmware-test pytest

lint:
	$(VENV)/bin/ruff check .

# The generated protocol files (messages.py, protocol_generated.h) must match protocol/spec.toml.
protocol-check:
	$(PY) -m phantom.protocol.generate --check

# The firmware core's native unit tests, the C++ golden-vector test and a bounded libFuzzer run.
firmware-test:
	$(MAKE) -C firmware test PYTHON=$(abspath $(PY))

pytest:
	$(PY) -m pytest -q

clean:
	rm -rf firmware/build hil/harness/build .pytest_cache .ruff_cache
