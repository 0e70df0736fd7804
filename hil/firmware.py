"""The firmware image the simulator runs: where it is, building it, and finding its functions."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import phantom
from phantom import PhantomError


class FirmwareError(PhantomError):
    """The firmware image is missing and cannot be built, or is not an AVR image."""


def default_elf() -> Path:
    """``firmware/build/uno-bench/phantom.elf`` of the source checkout: the Uno image with TEST_HANG (the
    production image ``build/uno/`` refuses it), so that the bench can check the watchdog."""
    if phantom.SOURCE_ROOT is None:
        raise FirmwareError("no firmware sources in this install: pass the path of a firmware .elf explicitly")
    return phantom.SOURCE_ROOT / "firmware" / "build" / "uno-bench" / "phantom.elf"


def ensure_firmware(elf: str | Path | None = None) -> Path:
    """The firmware image to run: ``elf`` if given (it must exist), else the default, built if missing.

    Raises
    ------
    FirmwareError
        When the given image does not exist, or the default one is missing and the AVR toolchain is absent
        or ``make -C firmware`` fails.
    """
    if elf is not None:
        path = Path(elf)
        if not path.is_file():
            raise FirmwareError(f"the firmware image {path} does not exist: build it with `make -C firmware`")
        return path
    path = default_elf()
    if path.is_file():
        return path
    if shutil.which("avr-gcc") is None or shutil.which("make") is None:
        raise FirmwareError(
            f"the firmware image {path} is missing and the AVR toolchain (avr-gcc, make) is not installed: "
            "run scripts/bootstrap.sh, then `make -C firmware`"
        )
    result = subprocess.run(["make", "-C", str(path.parents[2])], capture_output=True, text=True)
    if result.returncode != 0 or not path.is_file():
        raise FirmwareError(
            f"`make -C firmware` did not produce {path}:\n{result.stdout[-2000:]}{result.stderr[-2000:]}"
        )
    return path


def mcu_of(elf: Path) -> str:
    """The simavr MCU name for an image: the Mega build lives under build/mega/, everything else is an Uno."""
    return "atmega2560" if "mega" in elf.parent.name else "atmega328p"


def function_addresses(elf: Path) -> dict[str, int]:
    """Byte address of every function in the image by its demangled name (``avr-nm -C``)."""
    nm = shutil.which("avr-nm")
    if nm is None:
        raise FirmwareError("avr-nm is not installed (package binutils-avr): run scripts/bootstrap.sh")
    result = subprocess.run([nm, "-C", "--defined-only", str(elf)], capture_output=True, text=True)
    if result.returncode != 0:
        raise FirmwareError(f"{elf} is not an AVR image avr-nm can read: {result.stderr.strip()}")
    addresses = {}
    for line in result.stdout.splitlines():
        address, kind, name = line.split(" ", 2)
        if kind in "tTwW":
            addresses.setdefault(name, int(address, 16))
    return addresses
