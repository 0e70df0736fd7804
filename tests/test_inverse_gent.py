"""The inverse on the physically valid calibration (builtin:calibrated), checked by independent forward solves.

The Gent chambers' pressure-volume curve has an inflection (soft, then stiffening as the chains lock): the
tangent at 3 kPa is flatter than the secant from rest, so an undamped Newton iteration bounced between the
pressure bound and near-rest pressures for ever. A coarse mesh (8 mm) keeps this quick and shows the same
curve; the figures on the scene's 4 mm mesh are in model/README.md.
"""

import numpy as np
import pytest

from phantom.model import PhantomModel, load_scene
from phantom.model.inverse import InverseSolver
from phantom.model.target import Target, UnreachableTargetError

#: a few Gent solves on an 8 mm mesh, about 15 s: left out of make check
pytestmark = pytest.mark.slow

COARSE_MM = 8.0
#: The accuracy the daemon needs, relative to the target (0.1 %).
VOLUME_TOLERANCE = 1e-3


@pytest.fixture(scope="module")
def model():
    return PhantomModel.from_scene(load_scene("builtin:calibrated"), mesh_size_mm=COARSE_MM)


def test_gent_tangent_compliance_matches_central_differences_of_forward_solves(model):
    pressures_pa = np.array([530.0, 1090.0, 1090.0])
    tangent = model.compliance(model.equilibrium(pressures_pa))
    step_pa = 5.0
    chamber = np.empty((3, 3))
    gland = np.empty(3)
    for j in range(3):
        plus = model.equilibrium(pressures_pa + step_pa * np.eye(3)[j])
        minus = model.equilibrium(pressures_pa - step_pa * np.eye(3)[j])
        chamber[:, j] = (plus.chamber_volumes_m3 - minus.chamber_volumes_m3) / (2 * step_pa)
        gland[j] = (plus.gland_volume_m3 - minus.gland_volume_m3) / (2 * step_pa)
    # central differences' truncation error at 5 Pa on a curve that changes over ~1 kPa: well under 0.1 %
    scale = np.abs(chamber).max()
    np.testing.assert_allclose(tangent.chamber_m3_per_pa, chamber, atol=1e-3 * scale)
    np.testing.assert_allclose(tangent.gland_m3_per_pa, gland, rtol=1e-3)


@pytest.mark.parametrize("volume_ml", [30.0, 35.0, 40.0])
def test_gent_inverse_reaches_bph_volumes_checked_by_a_forward_solve_from_rest(model, volume_ml):
    solver = InverseSolver(model, fidelity="full")
    result = solver.pressures_for(Target(gland_volume_m3=volume_ml * 1e-6))
    assert np.all(result.pressures_pa >= 0) and np.all(result.pressures_pa <= 3000.0)
    forward = PhantomModel.from_scene(load_scene("builtin:calibrated"),
                                      mesh_size_mm=COARSE_MM).equilibrium(result.pressures_pa)
    assert forward.gland_volume_m3 * 1e6 == pytest.approx(volume_ml, rel=VOLUME_TOLERANCE)
    assert result.predicted_gland_volume_m3 == pytest.approx(forward.gland_volume_m3, rel=VOLUME_TOLERANCE)


def test_gent_inverse_refuses_an_unreachable_volume_with_the_reachable_range(model):
    solver = InverseSolver(model, fidelity="full")
    with pytest.raises(UnreachableTargetError, match="unreachable") as raised:
        solver.pressures_for(Target(gland_volume_m3=45e-6))
    message = str(raised.value)
    assert "\n" not in message
    low_ml, high_ml = (float(value) for value in message.split(" give ")[1].split(" ml")[0].split(" to "))
    # the range's ends are the forward model at no pressure and at every chamber's limit
    assert low_ml == pytest.approx(model.rest_gland_volume_m3 * 1e6, abs=1e-3)
    assert high_ml == pytest.approx(model.equilibrium(np.full(3, 3000.0)).gland_volume_m3 * 1e6, abs=1e-3)
    assert high_ml < 45.0
