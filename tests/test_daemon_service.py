"""The daemon as a service: its systemd unit's sandbox and the udev rule that gives it the board's port (issue 23,
defects 2, 6 and 10).

``systemd-analyze security --offline=yes`` rates the unit file as it is, without installing or starting it (it
comes with Debian's systemd package: scripts/apt-packages.txt); a score of 3 or lower is "OK" in its words.
"""

import configparser
import re
import shutil
import subprocess
from pathlib import Path

HOST = Path(__file__).resolve().parent.parent / "host"
UNIT = HOST / "systemd" / "phantomd.service"
UDEV = Path(__file__).resolve().parent.parent / "firmware" / "udev" / "99-phantom.rules"
#: The exposure score the unit must stay at or under (systemd-analyze: 0 safe .. 10 unsafe; <= 3.9 is "OK").
EXPOSURE_GOAL = 3.0


def unit_options() -> dict[str, list[str]]:
    """Every ``[Service]`` option of the unit with all its values (an option may be given several times)."""
    options: dict[str, list[str]] = {}
    section = None
    for line in UNIT.read_text().splitlines():
        line = line.strip()
        if line.startswith("["):
            section = line
        elif section == "[Service]" and "=" in line and not line.startswith("#"):
            key, _, value = line.partition("=")
            options.setdefault(key, []).append(value)
    return options


def test_the_units_sandbox_scores_3_or_lower_in_systemd_analyze_security():
    analyze = shutil.which("systemd-analyze")
    assert analyze is not None, "no systemd-analyze: install Debian's systemd package (scripts/apt-packages.txt)"
    result = subprocess.run([analyze, "security", "--offline=yes", "--no-pager", str(UNIT)], capture_output=True,
                            text=True, timeout=60)
    found = re.search(r"Overall exposure level for phantomd\.service: ([0-9.]+)", result.stdout)
    assert found is not None, result.stdout + result.stderr
    assert float(found.group(1)) <= EXPOSURE_GOAL, result.stdout


def test_the_unit_reaches_the_boards_port_and_nothing_else_of_dev_and_has_file_descriptors_to_spare():
    options = unit_options()
    assert options["DevicePolicy"] == ["closed"]
    assert sorted(options["DeviceAllow"]) == ["char-ttyACM rw", "char-ttyUSB rw"]
    assert options["CapabilityBoundingSet"] == [""] and options["NoNewPrivileges"] == ["yes"]
    assert "SupplementaryGroups" not in options          # the port is the phantom group's, not dialout's
    assert int(options["LimitNOFILE"][0]) >= 4096
    # what the daemon needs must not be sandboxed away: numba writes executable memory, the port is a device
    for needed in ("MemoryDenyWriteExecute", "PrivateDevices", "PrivateUsers"):
        assert needed not in options


def test_the_udev_rule_gives_the_port_to_the_phantom_group_not_to_dialout():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    unit.read(UNIT)
    rules = [line for line in UDEV.read_text().splitlines() if line.startswith("SUBSYSTEM==")]
    assert len(rules) == 3
    for rule in rules:
        assert f'GROUP="{unit["Service"]["Group"]}"' in rule and 'MODE="0660"' in rule and "dialout" not in rule
