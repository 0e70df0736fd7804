"""Bad input to the daemon gets a one-line error, never a traceback, a restart loop or gigabytes of memory
(issue 23, defects 3 and 9): files are size-checked before they are read, text must be UTF-8, nesting is bounded,
a timeline's steps are bounded, and heavy requests wait in a bounded queue."""

from __future__ import annotations

import asyncio
import re
import resource
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from phantom.host.api import ApiError
from phantom.host.config import ConfigError, load_config
from phantom.host.handlers import HeavyRequests
from phantom.host.scenes import MAX_STEPS, parse_target, parse_timeline
from phantom.model.calibration.calibrate import CalibrationError, load_measurements
from phantom.model.errors import SceneError
from phantom.model.scene import read_scene_toml

CHAMBERS = ["chamber0", "chamber1", "chamber2"]
REPO = Path(__file__).resolve().parent.parent
PHANTOM = Path(sys.executable).with_name("phantom")


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@pytest.mark.parametrize("reader, error", [(load_config, ConfigError), (read_scene_toml, SceneError)])
def test_a_huge_sparse_file_is_refused_by_its_size_without_reading_it(tmp_path, reader, error):
    huge = tmp_path / "huge.toml"
    with open(huge, "wb") as handle:
        handle.truncate(2 * 2**30)                # 2 GB of zeros, sparse: no disk used
    before_mb = peak_rss_mb()
    started = time.monotonic()
    with pytest.raises(error, match="larger than 1 MiB"):
        reader(huge)
    assert time.monotonic() - started < 2.0
    assert peak_rss_mb() - before_mb < 50        # before: the whole file read, 4-6 GB


def test_a_config_file_that_never_ends_is_refused():
    with pytest.raises(ConfigError, match="larger than"):
        load_config("/dev/zero")


@pytest.mark.parametrize("reader, error", [(load_config, ConfigError), (read_scene_toml, SceneError)])
def test_toml_nested_100000_deep_is_an_error_not_a_recursion_crash(tmp_path, reader, error):
    path = tmp_path / "deep.toml"
    path.write_text("x = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(error, match="not valid TOML"):
        reader(path)


@pytest.mark.parametrize("encoding, words", [("latin-1", "not UTF-8 text"), ("utf-16", "it is UTF-16")])
def test_a_scene_not_in_utf8_says_so(tmp_path, encoding, words):
    path = tmp_path / "scene.toml"
    path.write_bytes("# prostate, 20 °C\n[[steps]]\nat_s = 0\nvolume_ml = 30\n".encode(encoding))
    with pytest.raises(SceneError, match=words):
        read_scene_toml(path)


def test_a_utf8_scene_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_bytes("[[steps]]\nat_s = 0\nvolume_ml = 30\n".encode("utf-8-sig"))
    assert read_scene_toml(path) == {"steps": [{"at_s": 0, "volume_ml": 30}]}


def test_a_timeline_of_too_many_steps_is_refused_before_it_is_checked():
    steps = [{"at_s": index, "volume_ml": 30.0} for index in range(MAX_STEPS + 1)]
    with pytest.raises(SceneError, match=f"at most {MAX_STEPS}"):
        parse_timeline(steps, CHAMBERS, "many")
    assert len(parse_timeline(steps[:MAX_STEPS], CHAMBERS, "enough").steps) == MAX_STEPS


def test_a_scene_file_of_too_many_steps_is_refused_before_it_is_parsed(tmp_path, monkeypatch):
    """Issue 23, defect 3: a 20,000-step scene (0.6 MB, under the size limit) was parsed whole by tomllib in a
    worker thread before its steps were counted, holding the GIL the daemon's loop and the link's loop need (56
    and 72 ms stalls in bench/daemon_stall.py). ``run_scene`` counts its ``[[steps]]`` headers first."""
    from phantom.host import handlers

    header = (REPO / "host" / "scenes" / "bph_growth.toml").read_text().split("[timeline]")[0].split("[[steps]]")[0]
    path = tmp_path / "many.toml"
    path.write_text(header + "[timeline]\nend_s = 20010\n" + "".join(
        f"[[steps]]\nat_s = {index}\nvolume_ml = 30.0\n" for index in range(20000)))

    def parsed(source):
        raise AssertionError(f"{source} was parsed")
    monkeypatch.setattr(handlers, "load_timeline_scene", parsed)
    with pytest.raises(SceneError, match=f"has 20000 steps; a scene may have at most {MAX_STEPS}"):
        handlers.prepare_scene(str(path), 1.0, CHAMBERS, {}, "running.toml")
    fine = tmp_path / "fine.toml"
    fine.write_text(header + "[timeline]\nend_s = 10\n[[steps]]\nat_s = 0\nvolume_ml = 30.0\n"
                    + "# [[steps]] in a comment is not a step\n" * (MAX_STEPS + 1))
    with pytest.raises(AssertionError, match="was parsed"):   # a scene within the limit goes on to be parsed
        handlers.prepare_scene(str(fine), 1.0, CHAMBERS, {}, "running.toml")


def test_heavy_requests_beyond_the_queue_are_answered_busy():
    async def scenario():
        heavy = HeavyRequests(in_flight=2, waiting=3)
        release = asyncio.Event()
        answered: list[str] = []

        async def request():
            try:
                async with heavy.slot("surface"):
                    await release.wait()
                answered.append("done")
            except ApiError as error:
                answered.append(error.code)

        tasks = [asyncio.create_task(request()) for _ in range(8)]
        await asyncio.sleep(0.05)
        release.set()
        await asyncio.gather(*tasks)
        return answered

    answered = asyncio.run(scenario())
    assert sorted(answered) == ["busy"] * 3 + ["done"] * 5


@pytest.mark.parametrize("raw, words", [
    ({"volume_ml": 5e-324}, "at least 0.001 ml"),                      # was ZeroDivisionError: internal
    ({"chamber_volumes_ml": [5e-324, None, None]}, "at least 0.001 ml"),
    ({"volume_ml": 30.0, "growth_ratio": {"\u00b2": 1.0}}, "unknown chamber"),   # '²'.isdigit(): was ValueError
])
def test_targets_that_gave_an_internal_error_are_refused_with_a_reason(raw, words):
    with pytest.raises(SceneError, match=words):
        parse_target(raw, CHAMBERS)


#: A JSON (or TOML) integer of 401 digits: no float holds it (``float(HUGE)`` raises OverflowError).
HUGE = 10**400


@pytest.mark.parametrize("raw, key", [
    ({"volume_ml": HUGE}, "volume_ml"),
    ({"pressures_kpa": [1, HUGE, 1]}, r"pressures_kpa\[1\]"),
    ({"chamber_volumes_ml": [None, HUGE, None]}, r"chamber_volumes_ml\[1\]"),
    ({"volume_ml": 30, "growth_ratio": {"chamber1": HUGE}}, r"growth_ratio\[chamber1\]"),
])
def test_an_integer_too_large_for_a_number_is_refused_like_any_bad_number(raw, key):
    """A 401-digit integer (JSON and TOML allow any) was an OverflowError, answered ``internal``."""
    with pytest.raises(SceneError, match=f"{key} must be a finite number.*got an integer of about 401 digits") as error:
        parse_target(raw, CHAMBERS, "set_target")
    assert "\n" not in str(error.value) and len(str(error.value)) < 200


def _api_handlers():
    from phantom.host.handlers import ApiHandlers

    daemon = SimpleNamespace(chamber_names=CHAMBERS, chamber_labels=["base", "left lobe", "right lobe"])
    return ApiHandlers(daemon)  # type: ignore[arg-type]


@pytest.mark.parametrize("method, params, words", [
    ("set_target", {"volume_ml": HUGE}, "volume_ml must be a finite number"),
    ("set_target", {"pressures_kpa": [HUGE, 1, 1]}, r"pressures_kpa\[0\] must be a finite number"),
    ("surface", {"pressures_kpa": [1, 1, HUGE]}, r"pressures_kpa\[2\] must be a finite number"),
    ("run_scene", {"path": str(REPO / "host" / "scenes" / "bph_growth.toml"), "time_scale": HUGE},
     "time_scale must be a finite number"),
    ("run_scene", {"path": "/tmp/a\u0000b"}, "is not a valid path: it holds a null character"),
])
def test_requests_that_were_answered_internal_are_invalid_params(method, params, words):
    """Each was a bug in the daemon's answer (code ``internal``): an OverflowError or ValueError out of a handler."""
    handler = _api_handlers().table()[method]
    with pytest.raises(ApiError) as error:
        asyncio.run(handler(params))
    assert error.value.code == "invalid_params", error.value
    assert re.search(words, str(error.value)), error.value


MEASUREMENTS = "# pressures and volumes, 20 °C\np0_kpa,p1_kpa,p2_kpa,measured_ml\n0,0,0,26.1\n1,1,1,30.2\n2,2,2,34.5\n"


@pytest.mark.parametrize("encoding, words", [("latin-1", "not UTF-8 text"), ("utf-16", "it is UTF-16")])
def test_a_measurement_table_not_in_utf8_says_so(tmp_path, encoding, words):
    path = tmp_path / "measured.csv"
    path.write_bytes(MEASUREMENTS.encode(encoding))          # was a UnicodeDecodeError traceback
    with pytest.raises(CalibrationError, match=words):
        load_measurements(path, 3)


def test_a_measurement_table_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "measured.csv"
    path.write_bytes(MEASUREMENTS.encode("utf-8-sig"))       # was "needs columns p0_kpa...; it has ['\ufeffp0_kpa'"
    assert len(load_measurements(path, 3).volumes_m3) == 3


def test_a_huge_measurement_table_is_refused_by_its_size(tmp_path):
    huge = tmp_path / "huge.csv"
    with open(huge, "wb") as handle:
        handle.truncate(2 * 2**30)
    with pytest.raises(CalibrationError, match="larger than 1 MiB"):
        load_measurements(huge, 3)


def test_an_unwritable_recording_stops_the_start_with_one_line(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    started = subprocess.run([str(PHANTOM), "daemon", "--port", str(tmp_path / "no-board"), "--socket",
                              str(tmp_path / "d.sock"), "--rerun-save", str(blocker / "run.rrd")],
                             capture_output=True, text=True, timeout=120)
    assert started.returncode == 2
    errors = [line for line in started.stderr.splitlines() if line.startswith("phantom daemon: error:")]
    assert errors == [started.stderr.strip().splitlines()[-1]] and "Traceback" not in started.stderr
    assert not (tmp_path / "d.sock").exists()
