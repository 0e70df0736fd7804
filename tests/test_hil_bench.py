"""The bench's parts that need no simulated board: its step metrics against analytic responses, and the
refusals of bad input by the metrics, by the simulated board and by ``phantom hil`` before a board starts
(test_hil_sim.py runs the bench against the firmware in simavr)."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from phantom import PhantomError
from phantom.hil import bench
from phantom.hil.sim import SimulatedBoard


def test_step_metrics_match_analytic_responses():
    """First order p = A (1 - exp(-t/tau)): rise tau ln 9, 2 % settling tau ln 50, no overshoot. Second order
    with damping z: overshoot exp(-z pi / sqrt(1 - z^2)). Sampled at 1 ms, so times are good to about 1 ms.
    A noise spike late in the record moves the raw settling time but not the smoothed one."""
    t = np.arange(0, 3, 1e-3)
    tau = 0.2
    first = bench.step_metrics(t, 2.0 * (1 - np.exp(-t / tau)), 2.0)
    assert first["rise_time_s"] == pytest.approx(tau * math.log(9), abs=1e-3)
    # smoothing over 50 ms scales the decaying error by sinh(x)/x with x = 25 ms / tau: a 0.5 ms shift
    assert first["settling_time_s"] == pytest.approx(tau * math.log(50), abs=1e-3)
    assert first["settling_time_raw_s"] == pytest.approx(tau * math.log(50), abs=1e-3)
    assert first["overshoot_pct"] == 0.0
    # the last 20 % (t >= 2.4 s) still lacks 2 exp(-2.4 / 0.2) kPa at most
    assert 0 < first["steady_state_error_kpa"] < 2 * math.exp(-2.4 / tau)
    zeta, omega = 0.3, 20.0
    damped = omega * math.sqrt(1 - zeta**2)
    second = 1 - np.exp(-zeta * omega * t) * (np.cos(damped * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(damped * t))
    metrics = bench.step_metrics(t, second, 1.0)
    assert metrics["overshoot_pct"] == pytest.approx(100 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2)), rel=1e-3)
    spiked = 2.0 * (1 - np.exp(-t / tau))
    spiked[2000] += 0.1
    with_spike = bench.step_metrics(t, spiked, 2.0)
    assert with_spike["settling_time_raw_s"] == pytest.approx(2.001)
    assert with_spike["settling_time_s"] == pytest.approx(tau * math.log(50), abs=1e-3)
    never = bench.step_metrics(t, 0.5 * (1 - np.exp(-t / tau)), 1.0)
    assert never["settling_time_s"] is None and never["rise_time_s"] is None


def test_step_metrics_refuse_bad_input():
    with pytest.raises(bench.BenchError, match="at least 5 samples"):
        bench.step_metrics([0, 1], [0, 1], 1.0)
    with pytest.raises(bench.BenchError, match="must be > 0 kPa"):
        bench.step_metrics(np.arange(10), np.arange(10), 0.0)


@pytest.mark.slow
def test_simulated_board_refuses_bad_use(tmp_path):
    with pytest.raises(PhantomError, match="does not exist"):
        SimulatedBoard(elf=tmp_path / "missing.elf")
    with pytest.raises(PhantomError, match="speed must be a number >= 0"):
        SimulatedBoard(speed=-1)
    idle = SimulatedBoard()
    with pytest.raises(PhantomError, match="not started"):
        idle.port  # noqa: B018
    with pytest.raises(PhantomError, match="not started"):
        idle.plant_state()
    with pytest.raises(PhantomError, match="not started"), idle.resetting_on_open():
        pass


def test_cli_refuses_cycles_on_a_real_port_and_a_missing_port(tmp_path):
    phantom = Path(sys.executable).with_name("phantom")
    cycles = subprocess.run([str(phantom), "hil", "cycles", "--port", str(tmp_path / "tty")], capture_output=True,
                            text=True, timeout=60)
    assert cycles.returncode == 2 and "need the simulator" in cycles.stderr
    bad_gains = subprocess.run([str(phantom), "hil", "step", "--sim", "--pid", "1,2"], capture_output=True, text=True,
                               timeout=60)
    assert bad_gains.returncode == 2 and "--pid takes three gains" in bad_gains.stderr
    missing = subprocess.run([str(phantom), "hil", "handshake", "--port", str(tmp_path / "tty")], capture_output=True,
                             text=True, timeout=60)
    assert missing.returncode == 2 and "cannot open the serial port" in missing.stderr
