"""The HIL report's presentation (hil/bench.py: plot_steps, format_report): the board named, the step
thresholds stated and applied, the plot written. The checks themselves are tested in test_hil_*.py."""

from __future__ import annotations

import math

import numpy as np

from phantom.hil import bench
from phantom.protocol.sensor import ADC_COUNT_KPA


def first_order_step(chamber: int, tau_s: float, target_kpa: float = 2.0, overshoot: float = 0.0) -> dict:
    """A step dict as check_step returns it, for p = A (1 - exp(-t/tau)) (+ a damped bump for overshoot)."""
    t = np.arange(0, 2.5, 0.01)
    p = target_kpa * (1 - np.exp(-t / tau_s)) + overshoot * target_kpa * np.sin(np.pi * t / 0.6) * (t < 0.6)
    metrics = bench.step_metrics(t, p, target_kpa)
    metrics.update(chamber=chamber, target_kpa=target_kpa, adc_count_kpa=ADC_COUNT_KPA,
                   trace={"time_s": t.tolist(), "pressure_kpa": p.tolist(), "drive_level": np.clip(
                       2 * (target_kpa - p), 0, 1).tolist()})
    return metrics


def report(board: str, steps: list[dict]) -> dict:
    return {"board": board, "steps": steps,
            "handshake": {"passed": True, "firmware_version": "0.2.0", "board": "UNO", "protocol_version": 1,
                          "spec_hash": "0x0", "reset_cause": "POWER_ON"},
            "faults": [], "line_noise": {"skipped": "needs --sim"},
            "watchdog": {"passed": True, "reset_cause": "WATCHDOG", "watchdog_fault_latched": True}}


def test_the_report_names_the_board_and_states_and_applies_the_step_thresholds():
    fast, slow = first_order_step(0, 0.1), first_order_step(1, 0.4)  # settle in 0.39 s and 1.56 s
    assert fast["settling_time_s"] < 1.0 < slow["settling_time_s"]
    text = bench.format_report(report("/dev/ttyACM0", [fast, slow]))
    assert text.splitlines()[0] == "# HIL bench report: real board on /dev/ttyACM0"
    assert "settling < 1 s, overshoot < 5 %, steady-state error < one ADC count (0.0543 kPa)" in text
    rows = [line for line in text.splitlines() if line.startswith(("| 0 |", "| 1 |"))]
    assert rows[0].endswith("| met |") and rows[1].endswith("| NOT met |")
    assert bench.format_report(report("simulated (simavr)", [])).startswith(
        "# HIL bench report: simulated board (simavr)")


def test_overshoot_beyond_the_threshold_is_not_met():
    bumpy = first_order_step(2, 0.05, overshoot=0.08)
    assert bumpy["overshoot_pct"] > 5 and not bench.step_within_thresholds(bumpy)


def test_plot_steps_writes_a_png(tmp_path):
    path = bench.plot_steps([first_order_step(0, 0.1), first_order_step(1, 0.3)], tmp_path / "steps.png",
                            board="simulated (simavr)")
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    assert math.isclose(bench._first_crossing_s(np.array([0.0, 1.0]), np.array([0.0, 2.0]), 0.5), 0.25)
