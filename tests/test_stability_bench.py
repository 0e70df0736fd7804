"""The stress benchmark's fast subset (bench/stability.py --quick): the coarse thick sphere below, at and above its
peak and under volume control past it against the closed form, the chamber-volume inverse at both ends of its
range with the default pressure bound past the peak, non-finite pressures, nu = 0.5, and E from 1e-9 to 1e9 kPa.
Each case checks its own bound; the script exits 1 when one is missed (the table says which)."""

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench" / "stability.py"


@pytest.mark.long  # about 30 s of solves, 35 s of CPU in make test's 20 minutes: make test-long runs it; make test
# checks the same closed form through and past the peak (tests/test_fem_limit_point.py)
def test_the_stress_benchmarks_fast_subset_meets_every_bound():
    finished = subprocess.run([sys.executable, str(BENCH), "--quick"], capture_output=True, text=True, timeout=900)
    print(finished.stdout)
    assert finished.returncode == 0, finished.stdout + finished.stderr
    rows = [line for line in finished.stdout.splitlines() if line.startswith("| sphere")]
    assert len(rows) >= 10 and all(line.rstrip().endswith("| yes |") for line in rows)
    assert any("refused, peak" in line for line in rows)
