"""``make -C firmware upload BOARD=uno PORT=sim``: the upload rehearsed on the simulated board.

The same ``make upload`` a user types for a real board, at the port of a simulated one: the AVR in simavr runs
the stock Arduino bootloader (Optiboot on the Uno, stk500v2 on the Mega) over the other image of its MCU (the
bench image under the phantom image, and the other way round), is reset as a USB port's DTR pulse resets a
board, and avrdude flashes and verifies the image through the bootloader; then the board must answer, as the
board the image is for. Nothing is rehearsed that a real upload does not do, except the reset (a pty has no DTR
line, so avrdude warns about TIOCMGET).

    python -m phantom.cli.sim_upload --board uno
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

#: The image a board starts on before the rehearsal flashes BOARD: the other image of its MCU.
STARTS_ON = {"uno": "uno-bench", "uno-bench": "uno", "mega": "mega-bench", "mega-bench": "mega"}


def main(argv: list[str] | None = None) -> int:
    from phantom import PhantomError
    from phantom.hil import bench
    from phantom.hil.firmware import build_folder
    from phantom.hil.link import BoardLink
    from phantom.hil.sim import SimulatedBoard
    from phantom.protocol.messages import ENUMS

    parser = argparse.ArgumentParser(prog="make -C firmware upload PORT=sim", description=__doc__.splitlines()[0])
    parser.add_argument("--board", choices=sorted(STARTS_ON), default="uno")
    args = parser.parse_args(argv)
    firmware = Path(__file__).resolve().parents[2] / "firmware"
    for image in (args.board, STARTS_ON[args.board]):  # built first: what make upload prints is avrdude's
        subprocess.run(["make", "--no-print-directory", "-C", str(firmware), image], check=True,
                       stdout=subprocess.DEVNULL)
    try:
        with SimulatedBoard(elf=build_folder() / STARTS_ON[args.board] / "phantom.elf", speed=1.0,
                            bootloader=True) as board:
            print(f"rehearsal: a simulated board (simavr, the stock bootloader, {STARTS_ON[args.board]} image) at "
                  f"{board.port}, reset when avrdude opens it as a USB port's DTR line resets a board:", flush=True)
            command = ["make", "--no-print-directory", "-C", str(firmware), "upload", f"BOARD={args.board}",
                       f"PORT={board.port}"]
            print("$ " + " ".join(command[:1] + command[2:]), flush=True)
            with board.resetting_on_open():
                uploaded = subprocess.run(command, timeout=180).returncode == 0
            if not uploaded:
                print("rehearsal: the upload failed (avrdude's output above)", file=sys.stderr)
                return 1
            with BoardLink(board.port) as link:
                hello = bench.start_session(link)
    except PhantomError as error:
        print(f"rehearsal: error: {error}", file=sys.stderr)
        return 2
    names = {value: name for name, value in ENUMS["board"].items()}
    print(f"rehearsal: flashed and verified; the board now runs it and answers as {names.get(hello['board'])} "
          f"(firmware {hello['firmware_major']}.{hello['firmware_minor']}.{hello['firmware_patch']}). "
          "On a real board: the same command with PORT=/dev/phantom.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
