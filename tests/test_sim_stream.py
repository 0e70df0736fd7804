"""The simulated rig's camera stream (phantom/cli/sim_stream.py, ``phantom sim-board --camera-stream``) closed while
a picture's shape is being solved: it ends at once, and its picture's thread says nothing of the solver it lost
(a traceback in the board's log at every stop would read as a failure). The board is a stand-in here, holding the
phantom beyond the shipped shapes' box so that each picture's shape is an FE solve; the stream's own server,
truth and cameras are real."""

from __future__ import annotations

import threading
import time
import urllib.request

import pytest

pytestmark = pytest.mark.slow  # an FE solve of the truth model in a worker process


class HeldBeyondTheShapes:
    """A board whose plant holds every chamber at 5 kPa (beyond the shipped shapes' 3 kPa) and its rig at rest."""

    def plant_state(self) -> dict[str, object]:
        return {"pressures_pa": [5000.0, 5000.0, 5000.0], "rig_deg": [0.0, 0.0]}


def test_a_stream_closed_mid_solve_ends_at_once_and_quietly(capfd):
    from phantom.cli.sim_stream import CameraStream

    stream = CameraStream(HeldBeyondTheShapes(), "127.0.0.1", 0).start()
    truth = stream._truth_shape
    # two readers: the second's picture waits for the first's, and asks its solve of a solver the close ended
    readers = [threading.Thread(target=lambda: urllib.request.urlopen(stream.urls()["phantom"], timeout=120).read(),
                                daemon=True) for _ in range(2)]
    for reader in readers:
        reader.start()
    deadline = time.monotonic() + 60
    while not truth.solving:                                              # the picture's solve has started
        assert time.monotonic() < deadline, "no solve started for a phantom beyond the shapes' box"
        time.sleep(0.05)
    time.sleep(1.0)
    assert truth.solves == 0                                              # still solving
    started = time.monotonic()
    stream.close()
    closed_s = time.monotonic() - started
    for reader in readers:
        reader.join(10)
    assert closed_s < 5.0, closed_s                                       # the server's 0.5 s poll, a kill
    assert not any(reader.is_alive() for reader in readers)               # the stream ended for its clients
    time.sleep(0.5)
    assert "Traceback" not in capfd.readouterr().err
