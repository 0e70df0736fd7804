"""The firmware image the simulator runs: where it is, building it, and finding its functions."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import phantom
from phantom import PhantomError


class FirmwareError(PhantomError):
    """The firmware image is missing and cannot be built, or is not an AVR image."""


#: The image the simulated board runs: the Uno's with TEST_HANG (the production image refuses it), so that the
#: bench can check the watchdog.
DEFAULT_IMAGE = "uno-bench"
#: Where a wheel install keeps the firmware's sources (pyproject.toml maps firmware/ to this package folder).
PACKAGED_SOURCES = Path(__file__).resolve().parent / "firmware_sources"


def firmware_sources() -> Path:
    """The firmware's sources: ``firmware/`` of the checkout, else the copy a wheel carries."""
    if phantom.SOURCE_ROOT is not None:
        return phantom.SOURCE_ROOT / "firmware"
    if (PACKAGED_SOURCES / "Makefile").is_file():
        return PACKAGED_SOURCES
    raise FirmwareError("no firmware sources in this install: pass the path of a firmware .elf explicitly")


def build_folder() -> Path:
    """Where the images are built: ``firmware/build`` of the checkout, else the cache (a wheel's package folder
    may not be writable)."""
    if phantom.SOURCE_ROOT is not None:
        return firmware_sources() / "build"
    return phantom.cache_dir("firmware")


def default_elf() -> Path:
    """``build/uno-bench/phantom.elf`` (see :data:`DEFAULT_IMAGE`) under :func:`build_folder`."""
    firmware_sources()  # no sources, no image to build: say so here
    return build_folder() / DEFAULT_IMAGE / "phantom.elf"


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
    if path.is_file() and not _older_than_its_sources(path):
        return path
    if shutil.which("avr-gcc") is None or shutil.which("make") is None:
        raise FirmwareError(
            f"the firmware image {path} is missing and the AVR toolchain (avr-gcc, make) is not installed: "
            "run scripts/bootstrap.sh, then `make -C firmware`"
        )
    # a checkout builds every image (the tests run the Mega's too); a wheel the one it runs, into the cache
    command = ["make", "-C", str(firmware_sources())] if phantom.SOURCE_ROOT is not None else [
        "make", "-C", str(firmware_sources()), f"BUILD={build_folder()}", DEFAULT_IMAGE]
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0 or not path.is_file():
        raise FirmwareError(
            f"`{' '.join(command)}` did not produce {path}:\n{result.stdout[-2000:]}{result.stderr[-2000:]}"
        )
    return path


def _older_than_its_sources(elf: Path) -> bool:
    """Whether a checkout's image is older than a firmware source it is built from (a pull brought new sources or
    a new protocol spec: the stale image would answer in the old protocol); an installed wheel's never is."""
    if phantom.SOURCE_ROOT is None:
        return False
    built_s = elf.stat().st_mtime
    sources = [*firmware_sources().joinpath("src").rglob("*.*"), phantom.SOURCE_ROOT / "protocol" / "spec.toml"]
    return any(source.stat().st_mtime > built_s for source in sources if source.is_file())


#: Debian's arduino-core-avr: the bootloaders an Uno (Optiboot 4.4) and a Mega 2560 (stk500v2) ship with.
ARDUINO_BOOTLOADERS = Path("/usr/share/arduino/hardware/arduino/avr/bootloaders")
STOCK_BOOTLOADERS = {
    "atmega328p": ARDUINO_BOOTLOADERS / "optiboot" / "optiboot_atmega328.hex",
    "atmega2560": ARDUINO_BOOTLOADERS / "stk500v2" / "stk500boot_v2_mega2560.hex",
}
#: Optiboot's boot section on the ATmega328P: 512 bytes at the top of flash.
OPTIBOOT_START, FLASH_END_328P = 0x7E00, 0x8000


def hex_extent(path: Path) -> tuple[int, int]:
    """Lowest and one-past-highest address an Intel HEX file writes (data records only)."""
    base, low, high = 0, None, 0
    for line in path.read_text().split():
        count, address, kind = int(line[1:3], 16), int(line[3:7], 16), int(line[7:9], 16)
        if kind in (2, 4):
            base = int(line[9:13], 16) << (4 if kind == 2 else 16)
        elif kind == 0:
            low = base + address if low is None else min(low, base + address)
            high = max(high, base + address + count)
    return (low or 0), high


def stock_bootloader(mcu: str) -> Path:
    """The stock bootloader image of an MCU's Arduino board, from Debian's arduino-core-avr.

    The Mega's stk500v2 image is used as shipped. Debian's Optiboot image for the Uno is 532 bytes (built from
    Optiboot 4.4 with a newer avr-gcc): it overflows the 512-byte boot section, so its version word overwrites
    code and its last function lies past the end of flash; a real Uno cannot run it either. Then the same
    source, shipped in the package, is built as its Makefile's atmega328 target does but without the LED flashes
    at start (LED_START_FLASHES=0), which makes it fit (496 bytes); everything else (MCUSR, the 1 s watchdog
    wait after an external reset) is Optiboot 4.4 unchanged.

    Raises
    ------
    FirmwareError
        When the package or avr-gcc is missing, or the build fails.
    """
    path = STOCK_BOOTLOADERS[mcu]
    if not path.is_file():
        raise FirmwareError(f"the stock bootloader {path} is missing: install arduino-core-avr (scripts/bootstrap.sh)")
    if mcu != "atmega328p" or hex_extent(path)[1] <= FLASH_END_328P:
        return path
    out = phantom.cache_dir("hil") / "optiboot" / "optiboot_atmega328.hex"
    source = path.parent / "optiboot.c"
    if out.is_file() and out.stat().st_mtime >= source.stat().st_mtime:
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    elf = out.with_suffix(".elf")
    compile_line = [
        "avr-gcc", "-g", "-Wall", "-Os", "-fno-inline-small-functions", "-fno-split-wide-types", "-mshort-calls",
        "-mmcu=atmega328p", "-DF_CPU=16000000L", "-DBAUD_RATE=115200", "-DLED_START_FLASHES=0",
        f"-Wl,--section-start=.text={OPTIBOOT_START:#x}", "-Wl,--section-start=.version=0x7ffe", "-Wl,--relax",
        "-Wl,--gc-sections", "-nostartfiles", "-nostdlib", "-o", str(elf), str(source),
    ]
    objcopy_line = ["avr-objcopy", "-j", ".text", "-j", ".data", "-j", ".version", "--set-section-flags",
                    ".version=alloc,load", "-O", "ihex", str(elf), str(out)]
    for line in (compile_line, objcopy_line):
        if shutil.which(line[0]) is None:
            raise FirmwareError(f"{line[0]} is not installed (gcc-avr, binutils-avr): run scripts/bootstrap.sh")
        result = subprocess.run(line, capture_output=True, text=True)
        if result.returncode != 0:
            raise FirmwareError(f"building Optiboot from {source} failed:\n{result.stderr[-2000:]}")
    if hex_extent(out)[1] > FLASH_END_328P:
        raise FirmwareError(f"Optiboot built from {source} still does not fit its 512-byte boot section")
    return out


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
    addresses: dict[str, int] = {}
    for line in result.stdout.splitlines():
        address, kind, name = line.split(" ", 2)
        if kind in "tTwW":
            addresses.setdefault(name, int(address, 16))
    return addresses
