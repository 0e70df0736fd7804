# The two commands a newcomer needs: `make demo` and `make test`. Each sets itself up first
# (scripts/bootstrap.sh: Debian packages and .venv/), idempotently.
VENV := .venv
PY := $(VENV)/bin/python
CORES := $(shell nproc 2>/dev/null || echo 2)
# Python may write its bytecode caches (__pycache__/, ignored by git) whatever the environment says: with
# PYTHONDONTWRITEBYTECODE set (some images set it), every pytest worker rewrote the test modules' asserts and every
# `phantom` a test started compiled the package from source again (make check: 126 -> 113 s of CPU without it).
unexport PYTHONDONTWRITEBYTECODE

.PHONY: setup demo test check lint types protocol-check firmware-test firmware-test-one pytest pytest-fast test-long figures clean

setup:
	@scripts/bootstrap.sh

# The daemon drives the simulated phantom (the firmware image in simavr) through the BPH growth scene. It installs
# only what it uses (pyproject.toml's extra "demo") and builds only the image the simulated board runs (the Uno's
# with TEST_HANG, hil/firmware.py's DEFAULT_IMAGE).
demo:
	@scripts/bootstrap.sh --extras demo
	$(MAKE) -C firmware uno-bench
	$(PY) -m phantom.cli.demo --scene host/scenes/bph_growth.toml --time-scale 4 --out out

# The Debian packages first (the firmware's compilers among them); then the Python environment's install beside
# the firmware's builds and tests; then the checks that need the environment side by side (each is one process),
# on every core; then pytest.
test:
	@scripts/bootstrap.sh --packages-only
	@$(MAKE) --no-print-directory -j$(CORES) setup firmware-test
	@$(MAKE) --no-print-directory -j$(CORES) --output-sync=target lint types protocol-check
	@$(MAKE) --no-print-directory pytest

# The contributor's fast loop, under a minute: lint, types, the protocol check and the tests that need no
# simulator and take no long numerical case (pytest -m "not sim and not slow and not long"; mark a test that runs
# simavr with @pytest.mark.sim, one that takes seconds of numerics with @pytest.mark.slow, one of tens of minutes
# with @pytest.mark.long), side by side on every core.
check: setup
	@$(MAKE) --no-print-directory -j$(CORES) --output-sync=target lint types protocol-check pytest-fast

lint:
	$(VENV)/bin/ruff check .

# mypy on every package: the root, the CLI and each part (strictness per package in pyproject.toml). mypy cannot
# follow the editable install's import hook, so the package's folders are mapped into one tree under .cache/ first.
PARTS := $(wildcard protocol model scan shape host hil design)
MYPY_TREE := .cache/mypy-src/phantom
# mypy's cache lives with the project's other caches (phantom.cache_dir's root: $PHANTOM_CACHE_DIR, else
# $XDG_CACHE_HOME/phantom or ~/.cache/phantom), so a fresh clone on this machine starts warm: 36 s of CPU cold,
# 0.6 s warm. mypy checks each module's contents against the cache, so clones with different code share it safely.
MYPY_CACHE := $(or $(PHANTOM_CACHE_DIR),$(or $(XDG_CACHE_HOME),$(HOME)/.cache)/phantom)/mypy
types:
	@mkdir -p $(MYPY_TREE)
	@for f in __init__.py __main__.py cli; do ln -sfn ../../../phantom/$$f $(MYPY_TREE)/$$f; done
	@for d in $(PARTS); do ln -sfn ../../../$$d $(MYPY_TREE)/$$d; done
	$(VENV)/bin/mypy --cache-dir $(MYPY_CACHE) -m phantom -m phantom.__main__ -p phantom.cli $(addprefix -p phantom.,$(PARTS))

# The generated protocol files (messages.py, protocol_generated.h) must match protocol/spec.toml.
protocol-check:
	$(PY) -m phantom.protocol.generate --check

# The firmware core's native unit tests, the C++ golden-vector test and a bounded libFuzzer run. Its one Python
# script (the golden vectors to C++) needs the standard library only: make test runs this beside the Python
# environment's install (on a fresh machine pip's minute or two used one core of two).
firmware-test:
	$(MAKE) -C firmware test PYTHON=python3

# pytest on every core (pytest-xdist); tests/conftest.py schedules it (the modules whose tests share a fixture on one
# worker, the longest tests first).
PYTEST := $(PY) -m pytest -q -n auto

pytest-fast:
	$(PYTEST) -m "not sim and not slow and not long"

# Two pytests at once: the simavr tests at normal priority, the others at nice 5 (scripts/pytest-all.sh says why);
# each prints its slowest tests by the wall clock and by CPU time (--cpu-durations, tests/conftest.py).
pytest:
	PYTHON=$(PY) scripts/pytest-all.sh

# The tests of tens of minutes that make test leaves out (@pytest.mark.long): another phantom as the simulated
# board's truth, its plant built and a target verified against it.
test-long: setup
	$(PY) -m pytest -q -m long --durations=25

# Every image the docs show, made again by the commands their captions name (scripts/figures.py; minutes, not part
# of make test). Installs Debian's chromium first, for the Rerun screenshots.
figures:
	@scripts/bootstrap.sh scripts/apt-packages.txt scripts/apt-packages-figures.txt
	$(PY) scripts/figures.py

clean:
	rm -rf firmware/build hil/harness/build .pytest_cache .ruff_cache
