"""The examples a lab runs first, run as a lab would, against a daemon on the simulated board (the real firmware
in simavr) with the calibrated model: examples/inverse_targets.py steps through the paper's inverse targets, and
the notebook examples/first_hour.ipynb is executed cell by cell with nbclient (a scene, a matplotlib plot, the STL
surface)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import nbclient
import nbformat
import pytest
from daemon_rig import daemon_process

REPO = Path(__file__).resolve().parent.parent
PHANTOM = Path(sys.executable).with_name("phantom")

pytestmark = [pytest.mark.sim, pytest.mark.slow, pytest.mark.timeout(900)]


@pytest.fixture(scope="module")
def sim_daemon(tmp_path_factory, default_model_cached):
    """``phantom daemon --sim`` with its defaults (the calibrated model, its table from the cache)."""
    with daemon_process(tmp_path_factory.mktemp("examples"), "--sim", ready_s=120, stop_s=60) as daemon:
        yield {"socket": daemon.socket, "log": daemon.log_path}


def test_the_inverse_targets_script_prints_each_target_with_its_estimate_and_true_volume(sim_daemon):
    result = subprocess.run([sys.executable, str(REPO / "examples" / "inverse_targets.py"), "--socket",
                             str(sim_daemon["socket"])], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr + sim_daemon["log"].read_text()
    rows = {line.split()[0]: line.split() for line in result.stdout.splitlines() if line[:9].strip()[:1].isdigit()}
    for target in ("30.00", "35.00", "40.00", "45.00"):
        estimate, error_pct, true_ml = float(rows[target][1]), float(rows[target][2]), float(rows[target][3])
        assert abs(error_pct) <= 1.0 and estimate == pytest.approx(float(target), rel=0.01)
        # the simulated phantom is the measured one (its volume through the paper's Table I), which the model
        # misses by up to 9 % at a measured point (5.6 % at 45 ml in make demo): the true volume is printed
        # beside the estimate and is not the estimate
        assert abs(true_ml - float(target)) < 0.08 * float(target) and true_ml != estimate
    # below the model's rest volume (26.30 ml; the phantom measured 26.43): said so, with the range it reaches
    assert re.search(r"unreachable: .* reaches 26\.\d+-51\.\d+", " ".join(rows["26.00"])), rows["26.00"]


def test_the_notebook_runs_and_saves_its_plot_and_surface(sim_daemon, tmp_path):
    notebook = nbformat.read(REPO / "examples" / "first_hour.ipynb", as_version=4)
    os.environ["PHANTOM_SOCKET"] = str(sim_daemon["socket"])
    try:
        nbclient.NotebookClient(notebook, timeout=300, kernel_name="python3",
                                resources={"metadata": {"path": str(tmp_path)}}).execute()
    finally:
        del os.environ["PHANTOM_SOCKET"]
    outputs = [output for cell in notebook.cells if cell.cell_type == "code" for output in cell.outputs]
    text = "".join(output.get("text", "") for output in outputs)
    assert "link online" in text and "step 4: target 45.0 ml" in text
    assert any("image/png" in output.get("data", {}) for output in outputs), "the volume plot"
    stl_line = next(line for line in text.splitlines() if ".stl:" in line)
    stl = Path(stl_line.split(":")[0])
    assert stl.is_file() and stl.stat().st_size > 84 + 50 * 1000
