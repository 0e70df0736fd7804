"""The flashing path a lab uses, in CI: ``make -C firmware upload`` (avrdude) through the stock bootloader
(Optiboot on the Uno, stk500v2 on the Mega) running in simavr, over the simulated board's pty.

The board starts on the bench image; the phantom image is flashed over it, avrdude verifies it by reading it
back through the bootloader, and the board then runs it: it refuses TEST_HANG, which the bench image obeys.
A pty has no DTR line, so avrdude cannot reset the board as it does over USB (it warns about TIOCMGET and goes
on); the simulated board resets when avrdude opens its port, as the DTR pulse would
(``SimulatedBoard.resetting_on_open``).
"""

import os
import re
import shutil
import subprocess
import time

import pytest

from phantom.hil import bench
from phantom.hil.firmware import default_elf, ensure_firmware
from phantom.hil.link import BoardLink
from phantom.hil.sim import SimulatedBoard
from phantom.protocol.messages import CONSTANTS, ENUMS

pytestmark = [pytest.mark.sim, pytest.mark.timeout(240)]

#: The board's own boards: what `make upload` is told, and what its handshake says it is.
BOARDS = {"uno": "UNO", "mega": "MEGA2560"}


def upload(board: SimulatedBoard, board_name: str, env: dict[str, str] | None = None
           ) -> subprocess.CompletedProcess[str]:
    """`make -C firmware upload` at the simulated board's pty, the board reset when avrdude opens it (the DTR
    pulse)."""
    firmware = default_elf().parents[2]
    with board.resetting_on_open() as resets:
        result = subprocess.run(["make", "--no-print-directory", "-C", str(firmware), "upload",
                                 f"BOARD={board_name}", f"PORT={board.port}"], capture_output=True, text=True,
                                timeout=200, env=env)
    assert resets, "avrdude never opened the port"
    return result


@pytest.mark.parametrize("board_name", sorted(BOARDS))
def test_make_upload_flashes_the_phantom_image_through_the_stock_bootloader(board_name):
    ensure_firmware()  # the bench images the board starts on
    bench_elf = default_elf().parents[1] / f"{board_name}-bench" / "phantom.elf"
    with SimulatedBoard(elf=bench_elf, speed=1.0, bootloader=True) as board:
        result = upload(board, board_name)
        output = result.stdout + result.stderr
        assert result.returncode == 0, output
        written = re.search(r"(\d+) bytes of flash written", output)
        verified = re.search(r"(\d+) bytes of flash verified", output)
        assert written and verified and written.group(1) == verified.group(1), output
        assert int(written.group(1)) > 10_000  # the whole application, not a page
        # avrdude's last command leaves the bootloader, which starts what it wrote: the phantom image
        with BoardLink(board.port) as link:
            hello = bench.start_session(link)
            assert hello["board"] == ENUMS["board"][BOARDS[board_name]]
            answer = link.command("TEST_HANG", {"magic": CONSTANTS["TEST_HANG_MAGIC"]}, accept_nack=True)
            assert answer.name == "NACK" and answer.fields["status"] == ENUMS["status"]["BAD_MAGIC"]


def test_an_avrdude_that_starts_late_still_reaches_the_bootloader(tmp_path):
    """On a loaded machine avrdude may start a second or more after `make upload` does: longer than a stock bootloader
    listens after a reset (about a second, half of it avrdude's own start). The reset comes at avrdude's open of
    the port, as a DTR line gives it, so the upload still lands; a reset made as make started was spent (the
    Mega's upload failed so in a loaded make test)."""
    ensure_firmware()
    late = tmp_path / "avrdude"
    late.write_text(f'#!/bin/sh\nsleep 1.5\nexec {shutil.which("avrdude")} "$@"\n')
    late.chmod(0o755)
    with SimulatedBoard(elf=default_elf(), speed=1.0, bootloader=True) as board:
        result = upload(board, "uno", env={**os.environ, "PATH": f"{tmp_path}:{os.environ['PATH']}"})
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    assert re.search(r"(\d+) bytes of flash verified", output), output


@pytest.mark.slow
def test_make_upload_at_a_board_not_in_its_bootloader_fails_and_says_so():
    """Without the reset the application holds the port and ignores the programmer: avrdude gives up (after two
    sync attempts here, as AVRDUDE_FLAGS asks; its default ten take about a minute), and the upload fails rather
    than claiming a flash."""
    ensure_firmware()
    with SimulatedBoard(elf=default_elf(), speed=1.0, bootloader=True) as board:
        while board.plant_state()["control_since_s"] is None:  # past the bootloader's wait, in board time
            time.sleep(0.02)
        firmware = default_elf().parents[2]
        result = subprocess.run(["make", "--no-print-directory", "-C", str(firmware), "upload", "BOARD=uno",
                                 f"PORT={board.port}", "AVRDUDE_FLAGS=-xattempts=2"],
                                capture_output=True, text=True, timeout=180)
        assert result.returncode != 0
        assert "not in sync" in result.stderr or "not responding" in result.stderr, result.stderr
        assert "bytes of flash written" not in result.stderr


def test_the_upload_a_user_types_rehearses_on_the_simulated_board_with_port_sim():
    """`make -C firmware upload BOARD=uno PORT=sim`: the user's own command, at a simulated board in its stock
    bootloader; avrdude writes and verifies the phantom image, which then answers as an Uno."""
    firmware = default_elf().parents[2]
    result = subprocess.run(["make", "--no-print-directory", "-C", str(firmware), "upload", "BOARD=uno", "PORT=sim"],
                            capture_output=True, text=True, timeout=200)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    written = re.search(r"(\d+) bytes of flash written", output)
    verified = re.search(r"(\d+) bytes of flash verified", output)
    assert written and verified and written.group(1) == verified.group(1), output
    assert "answers as UNO" in output
