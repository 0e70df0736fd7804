"""The Python API's client side without a board: no daemon at all, a daemon still starting (its API server
answering ``starting`` with its progress), and the pieces a script sees (errors, results). The API against the
simulated board is tests/test_python_api.py."""

import asyncio
import contextlib
import functools
import threading

import numpy as np
import pytest

import phantom
from phantom.host.api import ApiError, ApiServer
from phantom.host.client import ConnectionLostError, DaemonError, StartingError, UnreachableError


@contextlib.contextmanager
def served(server: ApiServer):
    """``server`` listening on an event loop in a thread of its own for the length of the block."""
    async def serve(ready: threading.Event, stop: threading.Event):
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
        yield
    finally:
        stop.set()
        thread.join(10)


def test_no_daemon_is_one_line_naming_the_socket(tmp_path):
    with pytest.raises(ConnectionLostError) as caught:
        phantom.connect(tmp_path / "none.sock")
    assert "\n" not in str(caught.value) and "none.sock" in str(caught.value)
    assert "phantom daemon" in str(caught.value)


@pytest.mark.parametrize("ready_timeout_s", [0.0, 1.0])
def test_a_daemon_still_starting_is_waited_for_then_reported_with_its_progress(tmp_path, ready_timeout_s):
    """A daemon that has not built its parts answers ``starting`` with what it is doing: connect waits for it
    (telling ``on_wait``) and gives up with that progress."""
    server = ApiServer(tmp_path / "d.sock", {})
    server.starting = lambda: ApiError("starting", "the daemon is still starting: loading the model of "
                                       "builtin:calibrated (12 s so far)", {"stage": "loading the model"})
    with served(server):
        told = []
        with pytest.raises(StartingError) as caught:
            phantom.connect(tmp_path / "d.sock", ready_timeout_s=ready_timeout_s, on_wait=told.append)
        assert "loading the model of builtin:calibrated" in str(caught.value)
        assert "\n" not in str(caught.value)
        if ready_timeout_s:
            assert "was not ready after 1 s" in str(caught.value) and told
        else:
            assert caught.value.data == {"stage": "loading the model"}


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


def test_a_socket_path_too_long_for_a_unix_socket_is_one_line_that_says_the_limit(tmp_path):
    """`phantom status --socket /tmp/<120 characters>.sock` gave an `OSError: AF_UNIX path too long` traceback."""
    path = tmp_path / ("x" * 120 + ".sock")
    with pytest.raises(phantom.PhantomError) as caught:
        phantom.connect(path)
    assert str(caught.value) == (f"the socket path {path} is {len(str(path))} bytes long: a Unix socket's path may "
                                 "be at most 107 bytes (on Linux); pass a shorter socket path")


class ParamsDaemon:
    """The daemon's side of ``set_target`` and ``surface`` without a model or a board: the API's own handlers
    (their checks of the params) on a daemon that answers with what it was asked."""

    chamber_names = ["chamber0", "chamber1", "chamber2"]
    chamber_labels = ["base", "left", "right"]

    def status(self):
        return {"ready": True, "link": "online", "control": "idle", "rest_volume_ml": 26.3, "pid": 1}

    async def set_target(self, target, tolerance_pct, verify):
        return {"target": {"asked": "volume"}, "pressures_kpa": [1.0, 1.0, 1.0], "predicted_volume_ml": 32.0,
                "predicted_chamber_volumes_ml": [4.0, 5.0, 5.0], "iterations": 1, "solve_time_s": 0.01}

    async def set_shape_target(self, shape, labels, refine_solves, tolerance_pct):
        return await self.set_target(None, tolerance_pct, None)


@pytest.fixture
def params_daemon(tmp_path):
    """A daemon (:class:`ParamsDaemon`) on a socket in a thread of its own; yields the socket and the params of
    each request as the daemon read them."""
    from phantom.host.handlers import ApiHandlers

    handlers = ApiHandlers(ParamsDaemon()).table()
    asked = []

    async def record(params, method):
        asked.append(params)
        if method == "surface":
            return {"positions_mm": [[0.0, 0.0, 0.0]], "triangles": [[0, 0, 0]], "pressures_kpa": None}
        return await handlers[method](params)

    with served(ApiServer(tmp_path / "d.sock", {method: functools.partial(record, method=method)
                                                for method in ("status", "set_target", "surface")})):
        yield tmp_path / "d.sock", asked


@pytest.mark.parametrize(("call", "says"), [
    pytest.param(lambda ph: ph.set_volume(32, tolerance_pct="1", wait=False), "tolerance_pct (how close the "
                 "estimate must come for the target to be reached, %) must be a number in (0, 100], got '1'",
                 id="tolerance_pct text"),
    pytest.param(lambda ph: ph.set_volume(32, timeout_s="5"), "timeout_s must be a positive number of seconds, got "
                 "'5'", id="timeout_s text"),
    pytest.param(lambda ph: ph.set_pressures(None, wait=False), "pressures_kpa must be a list of 3 numbers",
                 id="pressures None"),
    pytest.param(lambda ph: ph.set_volume(32, growth_ratio=[1, 2], wait=False), "growth_ratio must be a table",
                 id="growth_ratio a list"),
    pytest.param(lambda ph: ph.set_shape("gland.stl", labels=["a"], wait=False), "labels are the gland's labels in "
                 "a label map, a list of positive whole numbers, got ['a']", id="labels text"),
    pytest.param(lambda ph: ph.set_volume({1, 2}, wait=False), "set_target: set {1, 2} cannot be sent: give "
                 "numbers, text, lists and dicts (numpy's numbers and arrays too)", id="not JSON"),
])
def test_bad_arguments_are_the_projects_error_saying_what_was_wrong(params_daemon, call, says):
    """They were a bare TypeError or ValueError from inside the client."""
    socket, _ = params_daemon
    with phantom.connect(socket) as ph, pytest.raises(phantom.PhantomError) as caught:
        call(ph)
    assert says in str(caught.value) and "\n" not in str(caught.value)


def test_numpy_numbers_and_arrays_are_sent_as_json_numbers(params_daemon, tmp_path):
    """What a notebook passes: ``list(np.array([1, 1, 1], dtype=np.float32))`` was "not JSON serializable"."""
    socket, asked = params_daemon
    with phantom.connect(socket) as ph:
        ph.set_pressures(list(np.array([1, 1, 1], dtype=np.float32)), wait=False)
        ph.set_pressures(np.array([1.5, 1.0, 0.5]), wait=False, tolerance_pct=np.float32(2.0))
        ph.set_volume(np.float32(32.0), wait=False, growth_ratio={"chamber1": np.int64(2), "chamber2": np.float64(1)})
        ph.set_chamber_volumes([np.int64(4), None, np.float32(5.5)], wait=False)
        ph.set_shape(tmp_path / "gland.stl", labels=np.array([4, 5]), refine_solves=np.int64(1), wait=False)
        ph.surface(np.array([1, 1, 1], dtype=np.int64))
    assert asked[-6:] == [
        {"pressures_kpa": [1.0, 1.0, 1.0], "tolerance_pct": 1.0},
        {"pressures_kpa": [1.5, 1.0, 0.5], "tolerance_pct": 2.0},
        {"volume_ml": 32.0, "growth_ratio": {"chamber1": 2, "chamber2": 1.0}, "tolerance_pct": 1.0},
        {"chamber_volumes_ml": [4, None, 5.5], "tolerance_pct": 1.0},
        {"shape": str(tmp_path / "gland.stl"), "labels": [4, 5], "refine_solves": 1, "tolerance_pct": 1.0},
        {"pressures_kpa": [1, 1, 1]}]


@pytest.mark.parametrize("timeout_s", [-1, 0, float("nan"), "5"])
def test_a_request_timeout_that_is_not_a_positive_number_is_refused_before_connecting(tmp_path, timeout_s):
    """``request_timeout_s=-1`` connected, then said "did not answer within -1 s"."""
    with pytest.raises(phantom.PhantomError) as caught:
        phantom.connect(tmp_path / "none.sock", request_timeout_s=timeout_s)
    assert str(caught.value) == f"request_timeout_s must be a positive number of seconds, got {timeout_s!r}"


@contextlib.contextmanager
def another_program(path, answer: bytes):
    """A unix socket at ``path`` served by another program: to every line it gets, it answers ``answer``."""
    import socket

    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    listener.listen()
    listener.settimeout(0.2)
    stop = threading.Event()

    def serve():
        while not stop.is_set():
            try:
                connection, _ = listener.accept()
            except TimeoutError:
                continue
            with connection:
                connection.settimeout(0.2)
                while not stop.is_set():
                    try:
                        if not connection.recv(4096):
                            break
                    except TimeoutError:
                        continue
                    connection.sendall(answer)

    thread = threading.Thread(target=serve)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(10)
        listener.close()


@pytest.mark.parametrize("answer", [b"HTTP/1.1 400 Bad Request\r\n\r\n", b"[1, 2]\n", b'{"id": 1, "result": {}}\n',
                                    b'{"id": 1, "error": "boom"}\n', b'{"id": 1, "result": [1]}\n', b'"text"\n'])
def test_another_programs_socket_is_said_to_be_no_phantom_daemon(tmp_path, answer):
    """``phantom.connect()`` to a socket another program serves raised its raw parse errors (JSONDecodeError,
    AttributeError 'list', KeyError 'link', TypeError): it says the socket is not a phantom daemon's."""
    path = tmp_path / "other.sock"
    with another_program(path, answer), pytest.raises(DaemonError) as caught:
        with phantom.connect(path, ready_timeout_s=0.0, request_timeout_s=5.0) as lab:
            lab.status()
    assert caught.value.code == "not_a_daemon"
    message = str(caught.value)
    assert "\n" not in message and str(path) in message and "not a phantom daemon" in message, message
