"""bench/verify_rounds.py run by the tests (test code only): its rows as JSON, split into the verified and the
``verify="auto"`` targets, and what it printed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parents[1] / "bench" / "verify_rounds.py"
#: The auto targets after make demo's five verified volumes (ml).
AUTO_ML = "28,32.5,37.5,42.5,47"


def verify_rounds(tmp_path: Path, *options: str) -> tuple[list[dict[str, Any]], list[dict[str, Any]], str]:
    """Four seeds of ``bench/verify_rounds.py OPTIONS --auto AUTO_ML``: its verified rows, its auto rows, its
    output."""
    out = tmp_path / "rounds.json"
    run = subprocess.run([sys.executable, str(BENCH), "--seeds", "4", "--auto", AUTO_ML, "--json", str(out),
                          *options], check=True, timeout=800, capture_output=True, text=True)
    rows = json.loads(out.read_text())
    return ([row for row in rows if row["verify"] == "scan"], [row for row in rows if row["verify"] == "auto"],
            run.stdout)
