"""What the daemon checks the board against: its gains and limits, its setpoints, and its readings' stillness.

* :class:`BoardSettings`: the PID gains and the over-pressure limit the daemon sends to every chamber with
  SET_PID at each connection (the board keeps whatever SET_PID last set in its EEPROM, a bench session's
  included, and has no message that reads them back: so the daemon never uses them silently, it sets its own),
  and what ``status`` says of them and of their source.
* :class:`SetpointWatch`: the board reports its setpoints in every TELEMETRY frame; setpoints the daemon did not
  send (another program on the port, a board that lost its state) are a mismatch, which the daemon answers by
  venting.
* :class:`Stillness`: the board zeroes its sensors only when every reading has stayed within
  ``ZERO_STABLE_PA`` of where it was for ``ZERO_SETTLE_MS`` (PROTOCOL.md section 8); the daemon follows the
  same rule on the telemetry, so that it waits for a deflating phantom as long as it is still moving and says
  how far it is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from phantom.protocol.messages import CONSTANTS

#: The drive ceiling the daemon sets (65535 = full drive).
FULL_DRIVE = 65535
#: Telemetry frames in a row that must disagree with the daemon's setpoints before it acts (60 ms at 50 Hz): one
#: frame sampled before a command arrived is not a mismatch.
MISMATCH_FRAMES = 3
#: After the daemon changed the setpoints (sent, vented, zeroed), frames are not compared for this long (s of the
#: host's clock): a frame may have been sampled before the command arrived.
MISMATCH_GRACE_S = 0.25
#: Setpoints within this of each other are the same (Pa): the wire carries whole pascals.
SAME_SETPOINT_PA = 1.0


@dataclass(frozen=True)
class BoardSettings:
    """The PID gains and over-pressure limit the daemon gives every chamber (PROTOCOL.md, SET_PID)."""

    kp_per_kpa: float
    ki_per_kpa_s: float
    kd_s_per_kpa: float
    pressure_limit_pa: float

    def set_pid_fields(self, chamber: int) -> dict[str, Any]:
        """SET_PID's fields for one chamber."""
        return {"chamber": chamber, "kp_per_kpa": self.kp_per_kpa, "ki_per_kpa_s": self.ki_per_kpa_s,
                "kd_s_per_kpa": self.kd_s_per_kpa, "max_pressure_pa": int(round(self.pressure_limit_pa)),
                "max_drive": FULL_DRIVE}

    def to_json(self) -> dict[str, Any]:
        return {"kp_per_kpa": self.kp_per_kpa, "ki_per_kpa_s": self.ki_per_kpa_s, "kd_s_per_kpa": self.kd_s_per_kpa,
                "pressure_limit_kpa": self.pressure_limit_pa / 1e3, "max_drive": 1.0}


class SetpointWatch:
    """Compares the setpoints the board reports with the ones the daemon expects it to hold.

    ``expected_pa`` is None while the daemon does not know (right after a connection, while a command is in
    flight); :meth:`frame` then compares nothing.
    """

    def __init__(self) -> None:
        self.expected_pa: np.ndarray | None = None
        self._quiet_until_s = 0.0
        self._disagreeing = 0

    def expect(self, setpoints_pa: np.ndarray | None, now_s: float) -> None:
        """The daemon has just set (or no longer knows) what the board holds."""
        self.expected_pa = None if setpoints_pa is None else np.asarray(setpoints_pa, dtype=float)
        self._quiet_until_s = now_s + MISMATCH_GRACE_S
        self._disagreeing = 0

    def frame(self, board_setpoints_pa: np.ndarray, now_s: float) -> bool:
        """One telemetry frame's setpoints; True once they have disagreed for :data:`MISMATCH_FRAMES` frames."""
        if self.expected_pa is None or now_s < self._quiet_until_s:
            self._disagreeing = 0
            return False
        differs = float(np.max(np.abs(np.asarray(board_setpoints_pa, dtype=float) - self.expected_pa)))
        self._disagreeing = self._disagreeing + 1 if differs > SAME_SETPOINT_PA else 0
        return self._disagreeing >= MISMATCH_FRAMES


class Stillness:
    """The board's stillness rule for a zero, followed on the telemetry: how long (s of board time) every
    reading has stayed within ``ZERO_STABLE_PA`` of where it was."""

    stable_pa = float(CONSTANTS["ZERO_STABLE_PA"])
    needed_s = CONSTANTS["ZERO_SETTLE_MS"] / 1e3

    def __init__(self) -> None:
        self._reference_pa: np.ndarray | None = None
        self._since_s = 0.0
        self._now_s = 0.0
        self.moved_pa = 0.0

    def frame(self, board_time_s: float, pressures_pa: np.ndarray) -> None:
        pressures = np.asarray(pressures_pa, dtype=float)
        if self._reference_pa is not None and board_time_s >= self._now_s:
            self.moved_pa = float(np.max(np.abs(pressures - self._reference_pa)))
        if self._reference_pa is None or board_time_s < self._now_s or self.moved_pa > self.stable_pa:
            self._reference_pa, self._since_s = pressures, board_time_s
        self._now_s = board_time_s

    @property
    def still_for_s(self) -> float:
        return self._now_s - self._since_s if self._reference_pa is not None else 0.0

    @property
    def still(self) -> bool:
        return self.still_for_s >= self.needed_s
