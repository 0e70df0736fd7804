"""The flashing path a lab uses, in CI: ``make -C firmware upload`` (avrdude) through the stock bootloader
(Optiboot on the Uno, stk500v2 on the Mega) running in simavr, over the simulated board's pty.

The board starts on the bench image; the phantom image is flashed over it, avrdude verifies it by reading it
back through the bootloader, and the board then runs it: it refuses TEST_HANG, which the bench image obeys.
A pty has no DTR line, so avrdude cannot reset the board as it does over USB (it warns about TIOCMGET and goes
on); the test resets the simulated board just before avrdude starts, as the DTR pulse would.
"""

import re
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


def upload(board: SimulatedBoard, board_name: str) -> subprocess.CompletedProcess[str]:
    """`make -C firmware upload` at the simulated board's pty, the board reset just before (the DTR pulse)."""
    firmware = default_elf().parents[2]
    # the image up to date first, so that make goes straight to avrdude after the reset
    subprocess.run(["make", "--no-print-directory", "-C", str(firmware), board_name], check=True,
                   capture_output=True, timeout=600)
    board.reset("external")
    return subprocess.run(["make", "--no-print-directory", "-C", str(firmware), "upload", f"BOARD={board_name}",
                           f"PORT={board.port}"], capture_output=True, text=True, timeout=180)


@pytest.mark.parametrize("board_name", sorted(BOARDS))
def test_make_upload_flashes_the_phantom_image_through_the_stock_bootloader(board_name):
    ensure_firmware()  # the bench images the board starts on
    bench_elf = default_elf().parents[1] / f"{board_name}-bench" / "phantom.elf"
    with SimulatedBoard(elf=bench_elf, speed=1.0, bootloader=True) as board:
        time.sleep(0.3)
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


@pytest.mark.slow
def test_make_upload_at_a_board_not_in_its_bootloader_fails_and_says_so():
    """Without the reset the application holds the port and ignores the programmer: avrdude gives up (after two
    sync attempts here, as AVRDUDE_FLAGS asks; its default ten take about a minute), and the upload fails rather
    than claiming a flash."""
    ensure_firmware()
    with SimulatedBoard(elf=default_elf(), speed=1.0, bootloader=True) as board:
        time.sleep(2.0)  # past the bootloader's wait: the application runs
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
