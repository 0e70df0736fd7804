"""The daemon's first ``set`` after start, warmed against cold, and how fast an unreachable target is refused.

Builds the daemon's model side twice in this process from the default scene (builtin:calibrated): once as the
daemon does (``LoadedModel``, which warms the inverse up at start-up) and once cold (the same model and
``InverseSolver`` without the warm-up, as the daemon was before). Times, in each, the first volume target, the
next ones, and refusals of unreachable targets (80 ml, above the 44 ml reach, and 1e300 ml). The cold one runs
first, so that module imports count against it, as they did in a fresh daemon.

    .venv/bin/python bench/daemon_inverse_warm.py
"""

from __future__ import annotations

import time

from phantom.host.scenes import parse_target

CHAMBERS = ["chamber0", "chamber1", "chamber2"]
TARGETS_ML = [32.0, 35.0, 38.0, 41.0]
UNREACHABLE_ML = [80.0, 1e300]


def timed_ms(solve, volume_ml: float) -> tuple[float, str]:
    from phantom.model.inverse import UnreachableTargetError

    started = time.perf_counter()
    try:
        solve(parse_target({"volume_ml": volume_ml}, CHAMBERS))
        outcome = "solved"
    except UnreachableTargetError:
        outcome = "refused"
    return 1e3 * (time.perf_counter() - started), outcome


def cold_solve():
    """The daemon's model side without the warm-up (an InverseSolver straight from the model)."""
    from phantom.host.model_worker import LoadedModel
    from phantom.model import PhantomModel, load_scene
    from phantom.model.inverse import InverseSolver

    model = LoadedModel.__new__(LoadedModel)  # its pressures_for() on a solver that was never warmed
    model.scene = load_scene("builtin:calibrated")
    model.model = PhantomModel.from_scene(model.scene)
    model.solver = InverseSolver(model.model)
    model.estimator = model.solver.estimator
    return model.pressures_for


def main() -> None:
    from phantom.host.model_worker import LoadedModel

    rows = []
    cold = cold_solve()  # first: the warmed model's start-up would load what the cold one must load itself
    warmed = LoadedModel("builtin:calibrated", report=lambda text: None)
    for name, solve in (("cold (before)", cold), ("warmed at start-up", warmed.pressures_for)):
        first_ms, _ = timed_ms(solve, TARGETS_ML[0])
        later_ms = [timed_ms(solve, volume)[0] for volume in TARGETS_ML[1:]]
        refusals = [timed_ms(solve, volume) for volume in UNREACHABLE_ML]
        rows.append((name, first_ms, max(later_ms), *[ms for ms, _ in refusals]))
        assert all(outcome == "refused" for _, outcome in refusals)
    print("daemon's inverse on builtin:calibrated (fidelity updated), ms:")
    print(f"{'':<20} {'first set':>10} {'later (max)':>12} {'80 ml refused':>14} {'1e300 ml refused':>17}")
    for name, first_ms, later_ms, refused_ms, absurd_ms in rows:
        print(f"{name:<20} {first_ms:10.1f} {later_ms:12.1f} {refused_ms:14.1f} {absurd_ms:17.1f}")
    print(f"first set, cold / warm: {rows[0][1] / rows[1][1]:.1f}x")


if __name__ == "__main__":
    main()
