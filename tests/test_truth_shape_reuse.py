"""The simulated phantom's truth shape (hil/truth_shape.py) as a verified target's scans use it: a settled
phantom's ripple (an ADC count) reuses the last FE shape, scaled to the plant's exact volume at the pressures
asked, and the FE solves run in a process of their own (in the daemon's process they held its interpreter's
lock for seconds and its board link fell into DEAD_HOST during a scan)."""

import os

import pytest

pytestmark = pytest.mark.slow  # FE solves of the truth model in a worker process


def test_a_ripple_reuses_the_shape_at_the_plants_exact_volume_and_a_step_solves_again():
    from phantom.hil.plant import load_plant
    from phantom.hil.truth_shape import TruthShape
    from phantom.model.mesh.surface import enclosed_volume_ml

    truth, plant = TruthShape(), load_plant()
    truth.surface([0.0, 0.0, 0.0])
    assert truth.solves == 1
    worker = list(truth._solver.pool._processes)
    assert len(worker) == 1 and worker[0] != os.getpid()                  # solved in its own process
    rippled = truth.surface([0.054, 0.0, 0.08])                            # within 0.1 kPa: no solve
    assert truth.solves == 1
    assert enclosed_volume_ml(rippled) == pytest.approx(plant.truth_gland_volume_ml([54.0, 0.0, 80.0]), rel=1e-9)
    stepped = truth.surface([0.3, 0.0, 0.0])                               # a step: solved again
    assert truth.solves == 2
    assert enclosed_volume_ml(stepped) == pytest.approx(plant.truth_gland_volume_ml([300.0, 0.0, 0.0]), rel=1e-9)
