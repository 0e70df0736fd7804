# The two commands a newcomer needs: `make demo` and `make test`. Each sets itself up first
# (scripts/bootstrap.sh: Debian packages and .venv/), idempotently.
VENV := .venv
PY := $(VENV)/bin/python
PHANTOM := $(VENV)/bin/phantom

.PHONY: setup demo test lint pytest clean

setup:
	@scripts/bootstrap.sh

demo: setup
	$(PHANTOM) forward --scene builtin --pressures-kpa 1,1,1

test: setup lint pytest

lint:
	$(VENV)/bin/ruff check .

pytest:
	$(PY) -m pytest -q

clean:
	rm -rf firmware/build hil/harness/build .pytest_cache .ruff_cache
