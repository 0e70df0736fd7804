#!/usr/bin/env bash
# make test's pytest: two runs at once, each on every core (pytest-xdist), their lines prefixed [sim] and [rest].
#
# - [sim]: the tests that run the firmware in simavr (marked sim). They mostly wait on board time (a board paced to
#   the wall clock takes about a fifth of a core, hil/README.md) while a daemon beside it must answer the board
#   within its dead-host deadline (500 ms of wall clock at any --sim-speed), so they run at normal priority.
# - [rest]: every other test, at a lower priority (nice 5): it takes the CPU the boards leave, and a numerical test
#   cannot hold a core a daemon is waiting for. (One run of both kinds on more workers than cores latched
#   DEAD_HOST in two scans; on as many workers as cores, the workers sat in board time with a core idle.)
# - The tests that load every core on purpose (marked busy_cores: one busy process per core beside make demo's
#   daemon) run in [rest], so that their load is at nice 5 too: at normal priority it starved the [sim] daemons
#   beside them past their deadline (DEAD_HOST latched in a scene and a scan in a clean clone's make test).
#
# Each run prints its slowest tests by the wall clock and by CPU time (--cpu-durations, tests/conftest.py). The
# status is the first failing run's. Arguments are passed to both runs (e.g. -x, or -k EXPRESSION). A failed [sim]
# run's summary is printed again at the end: it ends minutes before [rest], and a log read from its tail (a CI's)
# would show only [rest]'s durations.
set -uo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-.venv/bin/python}
# not passed on: a test that runs make in firmware/ would take this path, relative to the root, as the firmware's
unset PYTHON
sim_log=$(mktemp)
trap 'rm -f "$sim_log"' EXIT

"$python" -m pytest -q -n auto -m "sim and not long and not busy_cores" --durations=15 --cpu-durations=15 "$@" 2>&1 \
    | sed -u 's/^/[sim] /' | tee "$sim_log" &
sim=$!
nice -n 5 "$python" -m pytest -q -n auto -m "(not sim or busy_cores) and not long" --durations=25 --cpu-durations=25 "$@" 2>&1 \
    | sed -u 's/^/[rest] /'
rest=$?
wait "$sim"
sim=$?
if [ "$sim" -ne 0 ]; then
    echo "[sim] FAILED (status $sim); its summary again:"
    sed -n '/short test summary info/,$p' "$sim_log"
    exit "$sim"
fi
exit "$rest"
