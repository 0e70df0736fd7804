"""The suite's own rules (tests/conftest.py), as pytest applies them to the collected tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: A plugin that prints each collected test's timeout marker as pytest-timeout reads it (the closest one).
SHOW_TIMEOUTS = """
def pytest_collection_finish(session):
    for item in session.items:
        marker = item.get_closest_marker("timeout")
        print("TIMEOUT", item.name, marker.args if marker else None, marker.kwargs if marker else None)
"""


def test_a_test_that_builds_into_the_machines_cache_is_timed_from_its_call_only(tmp_path):
    """On a cold cache the calibrated table's build (shipped with its scene since), in the setup of the first test
    that used it, took 293 s of the 300 s pytest-timeout gives a test (a clean clone's make test, two busy cores),
    and the test failed: a test that uses a build once per machine (conftest.MACHINE_BUILDS) is timed from its
    call; the others as before."""
    (tmp_path / "show_timeouts.py").write_text(SHOW_TIMEOUTS)
    path = os.pathsep.join(filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")]))
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "show_timeouts",
         "tests/test_daemon_inputs_more.py", "-k", "run_scene_beyond_the_range or reachable_start_up_scene_starts"],
        cwd=ROOT, capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": path})
    assert done.returncode == 0, done.stdout + done.stderr
    shown = {line.split()[1]: line.split(" ", 2)[2] for line in done.stdout.splitlines()
             if line.startswith("TIMEOUT ")}
    assert shown == {
        "test_phantom_daemon_run_scene_beyond_the_range_exits_2_with_one_line": "(300.0,) {'func_only': True}",
        "test_a_reachable_start_up_scene_starts": "None None"}, done.stdout


def test_the_suite_runs_without_pytests_cache(tmp_path):
    """``pytest -p no:cacheprovider`` (a read-only checkout): the durations kept for the next run's order are not
    kept, and the run says nothing of it (it ended in an AttributeError after the tests had passed)."""
    done = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                           "tests/test_conftest.py"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "Error" not in done.stderr, done.stdout + done.stderr
