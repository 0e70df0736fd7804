"""The Python API's client side without a board: no daemon at all, a daemon still starting (its API server
answering ``starting`` with its progress), and the pieces a script sees (errors, results). The API against the
simulated board is tests/test_python_api.py."""

import asyncio
import threading

import pytest

import phantom
from phantom.host.api import ApiError, ApiServer
from phantom.host.client import ConnectionLostError, StartingError, UnreachableError


def test_no_daemon_is_one_line_naming_the_socket(tmp_path):
    with pytest.raises(ConnectionLostError) as caught:
        phantom.connect(tmp_path / "none.sock")
    assert "\n" not in str(caught.value) and "none.sock" in str(caught.value)
    assert "phantom daemon" in str(caught.value)


@pytest.mark.parametrize("ready_timeout_s", [0.0, 1.0])
def test_a_daemon_still_starting_is_waited_for_then_reported_with_its_progress(tmp_path, ready_timeout_s):
    """A daemon that has not built its parts answers ``starting`` with what it is doing: connect waits for it
    (telling ``on_wait``) and gives up with that progress."""
    async def serve(ready: threading.Event, stop: threading.Event):
        server = ApiServer(tmp_path / "d.sock", {})
        server.starting = lambda: ApiError("starting", "the daemon is still starting: loading the model of "
                                           "builtin:calibrated (12 s so far)", {"stage": "loading the model"})
        await server.start()
        ready.set()
        while not stop.is_set():
            await asyncio.sleep(0.05)
        await server.close()

    ready, stop = threading.Event(), threading.Event()
    thread = threading.Thread(target=asyncio.run, args=(serve(ready, stop),))
    thread.start()
    try:
        ready.wait(10)
        told = []
        with pytest.raises(StartingError) as caught:
            phantom.connect(tmp_path / "d.sock", ready_timeout_s=ready_timeout_s, on_wait=told.append)
        assert "loading the model of builtin:calibrated" in str(caught.value)
        assert "\n" not in str(caught.value)
        if ready_timeout_s:
            assert "was not ready after 1 s" in str(caught.value) and told
        else:
            assert caught.value.data == {"stage": "loading the model"}
    finally:
        stop.set()
        thread.join(10)


def test_the_unreachable_range_is_the_answers_data_never_its_words():
    """Issue 48: no regular expression over refusal texts in the client: the range is the API error's data."""
    give = UnreachableError("unreachable", "the gland volume target 80.000 ml is unreachable: pressures between 0 "
                            "and [3, 3, 3] kPa give 25.950 to 43.740 ml; ask for a volume in that range",
                            {"gland_range_ml": [25.95, 43.74], "corrected": False})
    assert give.range_ml == (25.95, 43.74)
    words_only = UnreachableError("unreachable", "pressures between 0 and [3, 3, 3] kPa give 25.950 to 43.740 ml")
    assert words_only.range_ml is None
    assert UnreachableError("unreachable", "the volume QP did not solve").range_ml is None


def test_phantom_connect_is_the_hosts_client():
    from phantom.host import client

    assert phantom.connect.__doc__ and "wait" in phantom.connect.__doc__
    assert client.Phantom.set_volume.__doc__ and "Raises" in client.Phantom.set_volume.__doc__


def test_a_target_results_band_and_measurements_come_from_the_answer():
    from phantom.host.client import TargetResult

    answer = {"target": {"volume_ml": 35.0}, "pressures_kpa": [1.0, 1.5, 1.5], "predicted_volume_ml": 35.0,
              "predicted_chamber_volumes_ml": [5.0, 6.0, 6.0], "iterations": 3, "solve_time_s": 0.05}
    plain = TargetResult.from_json(answer)
    assert plain.band_ml is None and plain.measurements == 0 and plain.scanned is None
    corrected = TargetResult.from_json({**answer, "band_ml": 0.07, "measurements": 12})
    assert corrected.band_ml == 0.07 and corrected.measurements == 12
