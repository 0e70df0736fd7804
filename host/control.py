"""The daemon's control without I/O: what the board should hold, when to solve, send, vent, and when a target
is reached. Shaped like :mod:`phantom.protocol.link`: it never reads a clock, sleeps or touches the board or the
model. The driver (host/daemon.py) feeds it events with their time and performs the actions it takes out.

Inputs (each takes ``now``, seconds on the daemon's monotonic clock)::

    offer(request, target, answer, tolerance_pct)   an API target, already solved: sent, and only once the board
                                                    has acknowledged it does it replace what was held
    want(target, source, step, ramp)                a scene's target in force (a step, or a point of its ramp)
    solved / solve_failed                           the inverse's answer to a Solve action
    sent / send_failed                              the board's answer to a SendSetpoints action
    vent / vent_done                                a vent decided (a request, a mismatch, a refusal); its answer
    board(ready, why)                               whether the board can take setpoints (online and configured)
    board_restarted(why)                            the board started again (its clock went back): it holds nothing
    faults(names)                                   the latched faults the telemetry shows
    zeroing(why)                                    a zero of the sensors in progress (setpoints would cancel it)
    board_setpoints(setpoints_pa)                   the setpoints a telemetry frame says the board holds
    measured(pressures_pa) / estimated(gland, chambers)   what reached is judged on
    scene_started / scene_ended                     the scene runner's state
    model_changed                                   the model answers on another level: solve again
    scanned(round, volume_ml, error, link_lost)     a verified target's scan, reconstructed (or why it failed)
    corrected(round, answer, how) / correct_failed  the pressures of a verified target's next round
    tick                                            retries and what waits

Actions (:meth:`ControlCore.take_actions`): :class:`Solve`, :class:`SendSetpoints`, :class:`SendVent`,
:class:`Tell` (an event for people, with an ``outcome`` for the targets clients wait on), :class:`StepApplied`,
:class:`StepReached`, :class:`StepUnreachable`, :class:`StopScene`, :class:`ConfigureBoard`, :class:`Answer` (the
reply to an API request), and a verified target's :class:`~phantom.host.verify.Scan`,
:class:`~phantom.host.verify.StopScan`,
:class:`~phantom.host.verify.Correct` and :class:`~phantom.host.verify.Record` (the verify policy's types,
host/verify.py, below the core).

Setpoints on the board that the daemon did not send (another program on the port, a board that lost its state)
are a mismatch (:class:`phantom.host.board_watch.SetpointWatch`): the core vents and has the board's gains and
limits set again.

One send at a time: a vent decided while setpoints are in flight goes out when they are answered. One definition
of reached (:class:`ReachRule`): the pressures within ``settled_kpa`` of the setpoints for ``settled_for_s``, and
the estimate within ``tolerance_pct`` of what was asked.

Reached is told once per target. A board that loses the setpoints of a reached target interrupts it
(:attr:`ControlCore.target_after_interruption`, with what it came ``after``): a fault latched (``fault``: the board
sets every setpoint to 0), a board that restarted (``board restart``: its clock went back, :meth:`board_restarted`;
it starts with none), or a link lost after which the board reports setpoints that are not the target's (``link
loss``). The target is then ``not_held`` until the board acknowledged its setpoints again (sent once the fault is
cleared, or the board is back), then ``settling``, and once the same rule holds on them again (the estimate is not
asked of a target a scan verified: the scan measured the volume at these setpoints) the core tells it,
``held_again``: an event of kind ``target`` with ``held_again: true``, ``after`` and no ``outcome``, so that a
client waiting on a target is never woken by it. A link lost while the board kept the target's setpoints (its
first frame since reports them, and it did not restart) interrupted nothing: its state, unknown while the board is
away (:attr:`ControlCore.awaits_board_frame`), is decided by that frame or by the restart the driver sees in it.

A verified target (:class:`Verify`, ``set_target``'s ``verify: "scan"``) is reached on pressure as any other;
then, instead of its ``reached`` outcome, the core asks for a :class:`Scan` of the phantom at the settled
pressures. A scanned gland volume within the share of the tolerance a round aims at (0.6 of it, a third for a scan
whose hull's error could not be taken off: :func:`phantom.host.verify.aim_share`; on the last round, within the
tolerance; :func:`phantom.host.verify.judge_scan`) ends it ``reached`` with the scanned volume (the volume reported
is MEASURED) and asks for a :class:`Record` of the scan as a measurement; one outside asks for a :class:`Correct`
(the scan recorded as a measurement, the next round's pressures solved), applies that answer, and scans again, up to
the round limit (then ``not_verified``, the last scan recorded). A failed scan ends it ``scan_failed``: no
correction from it, the pressures held; one that failed while the board's link was lost is taken again once the
pressures have settled (:data:`SCAN_RETRIES`). The rounds are in the outcome's ``rounds``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from phantom.host.board_watch import SAME_SETPOINT_PA, SetpointWatch
from phantom.host.config import DaemonConfig
from phantom.host.parts import ControlState
from phantom.host.verify import DOING_WORDS, SCAN_RETRIES, Correct, Record, Rounds, Scan, StopScan, Verify
from phantom.model.target import ML_PER_M3, PA_PER_KPA, InverseResult, Target

#: After a target could not be sent (refused, not acknowledged), how long the core waits before it tries again (s).
RETRY_S = 0.5
#: The highest setpoint the wire carries (Pa, i16).
MAX_SETPOINT_PA = 32767.0
#: What interrupted a reached target (:attr:`ControlCore.target_after_interruption`'s ``after``), in words: "held
#: again after ..."
AFTER_WORDS = {"fault": "the fault", "board restart": "the board restarted", "link loss": "the link was lost"}


@dataclass(frozen=True)
class ReachRule:
    """When a target counts as reached: every chamber's measured pressure (averaged over the estimate's window)
    within ``settled_kpa`` of its setpoint for ``settled_for_s``, and the estimate within ``tolerance_pct`` of the
    target (the gland volume, each given chamber volume, or for pressures the volume the inverse predicts)."""

    settled_kpa: float
    settled_for_s: float
    tolerance_pct: float = 1.0


#: A target's own ``tolerance_pct`` (``set_target``, ``phantom set --tolerance-pct``) is above 0 and at most this:
#: within 100 % of the target, anything the phantom holds is reached.
MAX_TOLERANCE_PCT = 100.0

#: The one rule of settled pressures and reached targets, from the daemon's settings' defaults (host/config.py:
#: the settled band is two ADC counts of the MPXV7025G); --settled-kpa, --settled-for-s and a target's own
#: tolerance_pct replace its values.
SETTLED = ReachRule(DaemonConfig.settled_kpa, DaemonConfig.settled_for_s)


class Settling:
    """The pressures settled, by a :class:`ReachRule`: every chamber within ``settled_kpa`` of its setpoint, for
    ``settled_for_s`` on the clock of the frames fed (the daemon's, or the board's for ``calibrate record``)."""

    def __init__(self, rule: ReachRule):
        self.rule = rule
        self.since_s: float | None = None

    def frame(self, time_s: float, measured_pa: np.ndarray, setpoints_pa: np.ndarray) -> float:
        """Feed one measurement; how long (s) the pressures have been settled up to it (0 when they are not)."""
        error_pa = np.abs(np.asarray(measured_pa, dtype=float) - np.asarray(setpoints_pa, dtype=float))
        if not np.all(error_pa <= self.rule.settled_kpa * PA_PER_KPA):
            self.since_s = None
            return 0.0
        if self.since_s is None:
            self.since_s = time_s
        return time_s - self.since_s

    def settled(self, time_s: float, measured_pa: np.ndarray, setpoints_pa: np.ndarray) -> bool:
        """:meth:`frame`, and whether that is long enough."""
        return self.frame(time_s, measured_pa, setpoints_pa) >= self.rule.settled_for_s


# --- actions ----------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Solve:
    """Ask the model for ``target``'s pressures (on ``ramp``, for a point of a scene's ramp)."""

    target: Target
    ramp: tuple[Target, Target] | None


@dataclass(frozen=True)
class SendSetpoints:
    """SET_SETPOINTS, acknowledged: ``setpoints_pa`` (whole Pa, 0..32767) for ``target``."""

    target: Target
    setpoints_pa: np.ndarray = field(compare=False)


@dataclass(frozen=True)
class SendVent:
    """VENT, acknowledged; ``request`` is the API request waiting on it (None: the daemon's own decision)."""

    why: str
    level: str
    request: int | None


@dataclass(frozen=True)
class Tell:
    """An event for people (status, Rerun, subscribers, the log); ``data`` carries a target's ``outcome``
    (reached, replaced, unreachable, faulted), its ``target`` and ``source``, for the clients that wait on it."""

    kind: str
    text: str
    level: str = "INFO"
    data: dict[str, Any] | None = None
    #: a verification's outcome: told once the scans it stored are stored (a client reading the phantom's
    #: measurements on it finds its last scan there)
    after_stored: bool = False


@dataclass(frozen=True)
class StepApplied:
    """The board acknowledged setpoints for scene step ``index``."""

    index: int


@dataclass(frozen=True)
class StepReached:
    """Scene step ``index`` was reached (:class:`ReachRule`)."""

    index: int


@dataclass(frozen=True)
class StepUnreachable:
    """Scene step ``index``'s target (or a point of its ramp) is beyond what the phantom reaches: ``text`` says
    why."""

    index: int
    text: str


@dataclass(frozen=True)
class StopScene:
    why: str


@dataclass(frozen=True)
class ConfigureBoard:
    """Set the board's gains and limits again (SET_PID), ``when`` says after what."""

    when: str


@dataclass(frozen=True)
class Answer:
    """The reply to API request ``request``: the inverse's answer, or an API error ``(code, text)``."""

    request: int
    result: InverseResult | None = None
    error: tuple[str, str] | None = None


Action = (Solve | SendSetpoints | SendVent | Tell | StepApplied | StepReached | StepUnreachable | StopScene
          | ConfigureBoard | Answer | Scan | StopScan | Correct | Record)


@dataclass
class _Offer:
    request: int
    answer: InverseResult
    tolerance_pct: float | None
    verify: Verify | None = None


@dataclass
class _Reach:
    """Progress of the target held towards reached."""

    target: Target
    source: str
    step: int | None
    tolerance_pct: float
    applied_s: float
    settling: Settling
    estimate: tuple[float, tuple[float, ...] | None] | None = None

    def again(self, now: float, rule: ReachRule) -> None:
        """Judged again from ``now`` (its setpoints sent again): the settling and the estimate start over."""
        self.applied_s, self.settling, self.estimate = now, Settling(rule), None


@dataclass
class _Away:
    """A reached target whose board went away (its link lost, or being set up again): whether the board kept
    its setpoints (``held_pa``) is decided by the first frame it sends once back, or by a restart."""

    held_pa: np.ndarray
    #: a frame since came with the target's setpoints while they were being sent again (kept, or landed)
    frames_seen: bool = False
    #: the target's setpoints sent again were acknowledged before any frame came (s): the next frame decides
    acked_s: float | None = None


def setpoints_for(pressures_pa: np.ndarray) -> np.ndarray:
    """The inverse's pressures (Pa) as the wire carries them: whole Pa within 0..32767."""
    return np.asarray([round(min(max(float(p), 0.0), MAX_SETPOINT_PA)) for p in pressures_pa], dtype=float)


def predicted_volume_ml(answer: InverseResult) -> float:
    """The gland volume (ml) the inverse predicts for its pressures."""
    return float(answer.predicted_gland_volume_m3) * ML_PER_M3


def estimate_within(target: Target, answer: InverseResult | None, gland_ml: float,
                    chamber_ml: tuple[float, ...] | None, tolerance_pct: float) -> bool:
    """The estimate within ``tolerance_pct`` of what was asked: the gland volume, each given chamber volume, or
    for raw pressures the volume the inverse predicts at them."""
    share = tolerance_pct / 100.0
    if target.kind == "chamber_volumes":
        if chamber_ml is None:
            return False
        return all(wanted_m3 is None or abs(got - wanted_m3 * ML_PER_M3) <= share * wanted_m3 * ML_PER_M3
                   for got, wanted_m3 in zip(chamber_ml, target.values, strict=True))
    if target.gland_volume_m3 is not None:
        wanted_ml = target.gland_volume_m3 * ML_PER_M3
    elif answer is not None:
        wanted_ml = predicted_volume_ml(answer)
    else:
        return False
    return abs(gland_ml - wanted_ml) <= share * wanted_ml


class ControlCore:
    """The target, its answer, what the board holds and why a target waits (module docstring)."""

    def __init__(self, chamber_count: int, rule: ReachRule | None = None, retry_s: float = RETRY_S):
        self.chamber_count = chamber_count
        self.rule = rule or SETTLED
        self.retry_s = retry_s
        self.state = ControlState.IDLE
        self.target: Target | None = None
        self.source: str | None = None
        self.step: int | None = None
        self.ramp: tuple[Target, Target] | None = None
        #: the reached tolerance asked with the current target (%), None: the rule's
        self.tolerance_pct: float | None = None
        #: the inverse's answer to the current target (None until solved)
        self.answer: InverseResult | None = None
        #: the target whose setpoints the board acknowledged and holds (None: unknown or none)
        self.applied: Target | None = None
        #: the setpoints the board holds as far as the daemon knows (Pa); None: unknown
        self.setpoints_pa: np.ndarray | None = None
        #: why the current target waits (None: it does not)
        self.pending: str | None = None
        self.vented_why: str | None = None
        self.board_ready = False
        self.board_why = "no board has been connected yet"
        self.fault_names: tuple[str, ...] = ()
        self.zeroing_why: str | None = None
        self.watch = SetpointWatch()
        self._pending_since_s: float | None = None
        self._retry_after_s = -np.inf
        self._unreachable: Target | None = None
        self._solving: Target | None = None
        self._sending: SendSetpoints | None = None
        self._offer: _Offer | None = None
        self._offer_sent: _Offer | None = None
        self._vent: SendVent | None = None
        self._venting = False
        #: a VENT the board could not be told (the link down): sent again once the board is back
        self._vent_waits_for_board = False
        self._reach: _Reach | None = None
        #: the target last told reached (not told again when the board takes it again)
        self._reached: Target | None = None
        #: whether that target's reached came from a scan (held again is then judged on the pressures alone)
        self._reached_scanned = False
        #: what became of the reached target after it was interrupted (:attr:`target_after_interruption`; None:
        #: not interrupted since), and after what (``fault``, ``board restart``, ``link loss``)
        self._held: str | None = None
        self._held_after: str | None = None
        #: the reached target's setpoints sent again after an interruption, judged by the reach rule until held again
        self._again: _Reach | None = None
        #: the reached target's board went away: whether it kept the setpoints is not known yet
        self._away: _Away | None = None
        self._measured: tuple[float, np.ndarray] | None = None
        #: the verified target's rounds (None: the target is not verified, or its verification ended)
        self._rounds: Rounds | None = None
        #: a ``verify = "auto"`` target the correction is sure of (no scan): its Verify and answer
        self._sure: tuple[Verify, InverseResult] | None = None
        self._actions: list[Action] = []

    # --- what the driver reads ----------------------------------------------------------------------------

    def take_actions(self) -> list[Action]:
        """The actions decided since the last call, in order."""
        actions, self._actions = self._actions, []
        return actions

    def next_deadline(self) -> float | None:
        """When :meth:`tick` has something to do (a retry that nothing else holds back), or None."""
        if (self.target is None or self.applied == self.target or self._retry_after_s == -np.inf or self.busy
                or self.solving or self._why_not_now() is not None):
            return None
        return float(self._retry_after_s)

    @property
    def busy(self) -> bool:
        """Whether a command to the board is in flight."""
        return self._sending is not None or self._venting

    @property
    def solving(self) -> bool:
        """Whether a solve for the core is in flight."""
        return self._solving is not None

    @property
    def verifying(self) -> bool:
        """Whether a verified target is being scanned or corrected (a scene's clock waits meanwhile)."""
        return self._rounds is not None and bool(self._rounds.rounds)

    @property
    def verify_progress(self) -> dict[str, Any] | None:
        """Where the verified target's rounds are (:meth:`phantom.host.verify.Rounds.progress`), None while no
        target is verified."""
        return None if self._rounds is None else self._rounds.progress()

    @property
    def target_after_interruption(self) -> dict[str, str] | None:
        """What became of the target in force after the board lost its setpoints once it was reached:
        ``{"state": ..., "after": ...}``, the state ``not_held`` (not acknowledged again yet), ``settling`` (its
        setpoints acknowledged again), ``held_again`` (the reach rule holds on them again: told once, as an event),
        after ``fault``, ``board restart`` or ``link loss``; None while nothing interrupted it since its reached."""
        if self.target is None or self._held is None or self._held_after is None:
            return None
        return {"state": self._held, "after": self._held_after}

    @property
    def awaits_board_frame(self) -> bool:
        """Whether the board came back (or is away) holding a reached target whose setpoints it may have lost,
        and no frame has said yet: the driver lets one come before the board is declared ready, so that it is
        judged on what the board held rather than on the setpoints sent again."""
        return self._away is not None and not self._away.frames_seen and self._away.acked_s is None

    @property
    def target_applied(self) -> bool:
        """Whether the board holds the current target's setpoints (acknowledged, not lost since)."""
        return self.target is not None and self.applied == self.target and self.board_ready

    # --- inputs -------------------------------------------------------------------------------------------

    def offer(self, now: float, request: int, answer: InverseResult, tolerance_pct: float | None = None,
              verify: Verify | None = None) -> None:
        """An API target, solved: sent when the board is free; on its ACK it replaces the target (and any scene);
        the request is answered then, or with the error that stopped it (nothing changed then). With ``verify``
        (a gland volume target) it is then verified by scans (module docstring)."""
        if not self.board_ready:
            self._actions.append(Answer(request, error=("link_down", f"no board: {self.board_why}; the target was "
                                                        "not set")))
            return
        self._drop_offer("replaced by a newer set_target before it was sent")
        self._offer = _Offer(request, answer, tolerance_pct, verify)
        self._next(now)

    def want(self, now: float, target: Target, source: str, step: int | None = None,
             ramp: tuple[Target, Target] | None = None, verify: Verify | None = None) -> None:
        """Aim at ``target`` (a scene's, while the state is ``scene``): applied as soon as the board can take it;
        with ``verify`` (a scene step's), verified by scans once reached."""
        if target == self.target and source == self.source:
            ramp_ended = self.ramp is not None and ramp is None
            self.step, self.ramp = step, ramp
            if ramp_ended and self.applied == target:
                self._start_reach(now)  # a ramp that ends on the point it last sent
            return
        self._set_target(now, target, source, step, ramp, None)
        self._sure = None
        if verify is not None and target.gland_volume_m3 is not None:
            self._rounds = Rounds(verify, target.gland_volume_m3 * ML_PER_M3, target.gland_volume_m3 * ML_PER_M3)
        self._next(now)

    def solved(self, now: float, target: Target, answer: InverseResult) -> None:
        if self._solving == target:
            self._solving = None
        if target == self.target:
            self.answer = answer
            rounds = self._rounds
            if rounds is not None and not rounds.rounds and not rounds.verify.needs_scan(answer, rounds.target_ml):
                self._sure, self._rounds = (rounds.verify, answer), None  # a scene step's verify = "auto"
        self._next(now)

    def solve_failed(self, now: float, target: Target, unreachable: bool, text: str,
                     gland_range_ml: tuple[float, float] | None = None) -> None:
        """The target could not be solved: ``unreachable`` (the gland's reachable range ``gland_range_ml`` goes
        with the outcome as data, when the model gave it), or the model failed (tried again)."""
        if self._solving == target:
            self._solving = None
        if target == self.target:
            if unreachable:
                self._unreachable = target
                if self.step is not None:
                    self._actions.append(StepUnreachable(self.step, f"target {target.describe()} is unreachable: "
                                                                    f"{text}"))
                self._wait(f"unreachable: {text}")
                self._outcome("unreachable", f"target {target.describe()} is unreachable: {text}", "WARN",
                              extra=None if gland_range_ml is None else {"gland_range_ml": list(gland_range_ml)})
            else:
                self._retry_after_s = now + self.retry_s
                self._wait(text)
        self._next(now)

    def sent(self, now: float, target: Target) -> None:
        """The board acknowledged the setpoints in flight (those of ``target``)."""
        sending, self._sending = self._sending, None
        if sending is None:
            return
        self.setpoints_pa, self.applied = sending.setpoints_pa, target
        self.watch.expect(self.setpoints_pa, now)
        away = self._away
        if away is not None and target == self._reached:
            if away.frames_seen:
                self._away = None  # a frame since showed them: kept (or landed first), nothing lost that was seen
            else:
                away.acked_s = now  # no frame yet: the next one (a restart, or not) decides
        offer, self._offer_sent = self._offer_sent, None
        if offer is not None and offer.answer.target == target:
            self.scene_ended(now, "a set_target request", stop=True)
            self.state = ControlState.HOLDING
            changed = target != self.target
            self._set_target(now, target, "api", None, None, offer.tolerance_pct)
            self._forget_reached()  # asked again: told again
            self.answer = offer.answer
            self._rounds = self._sure = None
            if offer.verify is not None and target.gland_volume_m3 is not None:
                target_ml = target.gland_volume_m3 * ML_PER_M3
                if offer.verify.needs_scan(offer.answer, target_ml):
                    self._rounds = Rounds(offer.verify, target_ml, target_ml)
                else:
                    self._sure = (offer.verify, offer.answer)
            if changed:
                pressures = ", ".join(f"{p / PA_PER_KPA:.3f}" for p in offer.answer.pressures_pa)
                self._tell("target", f"target {target.describe()} -> setpoints {pressures} kPa (predicted "
                           f"{predicted_volume_ml(offer.answer):.2f} ml, inverse "
                           f"{offer.answer.solve_time_s * 1e3:.1f} ms)")
            self._actions.append(Answer(offer.request, result=offer.answer))
        if target == self.target and self.state is not ControlState.VENTED:
            self._applied(now, target)
        self._next(now)

    def send_failed(self, now: float, target: Target, rejected: bool, text: str) -> None:
        """The setpoints in flight were refused (``rejected``: the board holds what it held) or not delivered
        (it is unknown what the board holds)."""
        sending, self._sending = self._sending, None
        if not rejected:
            self.setpoints_pa, self.applied = None, None
        self.watch.expect(self.setpoints_pa, now)
        offer, self._offer_sent = self._offer_sent, None
        if offer is not None and sending is not None and offer.answer.target == sending.target:
            self._actions.append(Answer(offer.request, error=("rejected" if rejected else "link_down", text)))
        elif target == self.target:
            self._retry_after_s = now + self.retry_s
            self._wait(text)
        self._next(now)

    def vent(self, now: float, why: str, level: str = "INFO", request: int | None = None) -> None:
        """Blowers off: every setpoint 0, the target and any scene dropped (the VENT goes when the board is free)."""
        self.scene_ended(now, "vented", stop=True)
        self._drop_offer("a vent came before it was sent")
        if self._offer_sent is not None:  # in flight: the vent goes after it and wins
            self._actions.append(Answer(self._offer_sent.request, error=("replaced", "a vent came before the board "
                                                                         "acknowledged it")))
            self._offer_sent = None
        self._replaced(f"vented: {why}")
        self._forget_reached()
        self.state = ControlState.VENTED
        self.target = self.source = self.answer = self.step = self.ramp = None
        self.pending, self._pending_since_s, self._unreachable = None, None, None
        self.vented_why = why
        if self._vent is not None and self._vent.request is not None:
            self._actions.append(Answer(self._vent.request))  # the VENT still to go answers both
        self._vent, self._vent_waits_for_board = SendVent(why, level, request), False  # asked: tried at once
        self._next(now)

    def vent_done(self, now: float, error: str | None, link_down: bool = False) -> None:
        """The VENT's answer: acknowledged (``error`` None), or why the board could not be told. With the link
        down (``link_down``) the VENT stays to go once the board is back (:meth:`board`): the target is dropped
        already, and the board, left without its keepalive, vents by itself at its dead-host deadline meanwhile."""
        vent, self._vent, self._venting = self._vent, None, False
        self.applied = None
        self.setpoints_pa = np.zeros(self.chamber_count) if error is None else None
        self.watch.expect(self.setpoints_pa, now)
        if vent is not None:
            if error is None:
                self._tell("vent", f"vented: {vent.why}", vent.level)
            elif link_down:
                error = (f"{error}: the target is dropped and the VENT goes to the board when it is back (a board "
                         "left without its host vents by itself at its dead-host deadline)")
                self._tell("vent", f"could not vent yet ({vent.why}): {error}", "WARN")
                self._vent, self._vent_waits_for_board = SendVent(vent.why, vent.level, None), True
            else:
                self._tell("vent", f"could not vent ({vent.why}): {error}", "ERROR")
            if vent.request is not None:
                self._actions.append(Answer(vent.request, error=None if error is None else ("link_down", error)))
        self._next(now)

    def board(self, now: float, ready: bool, why: str = "") -> None:
        """Whether the board can take setpoints (online, its gains and limits set); ``why`` it cannot. A board
        that comes back holds none of ours (it may have reset): the target is applied again; with none, the
        board must hold nothing."""
        if ready != self.board_ready:
            self._vent_waits_for_board = self._vent_waits_for_board and not ready
            if not ready:
                self._went_away()
            self.applied = None
            idle = self.target is None or self.state is ControlState.VENTED
            self.setpoints_pa = np.zeros(self.chamber_count) if ready and idle else None
            self.watch.expect(self.setpoints_pa, now)
            if self.target is not None and self._pending_since_s is None:
                self._pending_since_s = now
        self.board_ready, self.board_why = ready, why
        self._next(now)

    def faults(self, now: float, names: tuple[str, ...]) -> None:
        """The faults latched on the board now: a new one set every setpoint to 0 and refuses setpoints until
        cleared; the target is applied again once cleared."""
        if names == self.fault_names:
            return
        if names and not self.fault_names:
            self._tell("fault", f"faults latched: {', '.join(names)}", "ERROR")
            self.applied, self.setpoints_pa = None, np.zeros(self.chamber_count)
            self.watch.expect(self.setpoints_pa, now)
            if self.target is not None and self._pending_since_s is None:
                self._pending_since_s = now
            self._interrupted(now, "fault", "")  # told reached: no outcome, held again later
            if self._reach is not None:
                rounds, verifying = self._rounds, ""
                if rounds is not None:
                    # a fault mid-verify: which round, what it was doing, and what to do (the scans before are
                    # stored measurements: the next try starts from the correction they give)
                    doing = DOING_WORDS[rounds.doing or "settling"]
                    verifying = (f" during verify round {rounds.underway} of {rounds.verify.rounds} ({doing}); "
                                 f"the scans before are stored. Find why ({', '.join(names)}: `phantom status`, the "
                                 "daemon's log), clear it (`phantom clear-fault`), then set the target again")
                self._outcome("faulted", f"target {self._reach.target.describe()} not reached: faults latched "
                              f"({', '.join(names)}){verifying}", "ERROR",
                              extra=rounds.to_json() if verifying and rounds is not None else None)
        elif not names:
            self._tell("fault", "faults cleared")
        self.fault_names = names
        self._next(now)

    def zeroing(self, now: float, why: str | None) -> None:
        """A zero in progress (``why`` says how far), or over (None): setpoints wait meanwhile."""
        self.zeroing_why = why
        self._next(now)

    def board_restarted(self, now: float, why: str) -> None:
        """The board started again (``why``: its clock went back): it holds no setpoints; a reached target is
        interrupted (its setpoints go again once the link is back, as after any reconnection)."""
        away = self._away
        acked_s = None if away is None else away.acked_s
        self._interrupted(now, "board restart", f"the board restarted ({why}), so it held none of its setpoints")
        if acked_s is not None and self.target_applied:
            self._start_reach(acked_s)  # the setpoints sent again were taken after the restart: settling since

    def board_setpoints(self, now: float, setpoints_pa: np.ndarray) -> None:
        """The setpoints a telemetry frame reports: ones the daemon did not send vent the phantom. The first
        frames after a reached target's board went away say whether it kept the target's setpoints."""
        away = self._away
        if away is not None:
            lost = _differ(setpoints_pa, away.held_pa)
            if away.acked_s is not None or (not lost and self._sending is None):
                self._away = None  # kept (the setpoints acknowledged since, and no restart came with this frame)
            elif lost:
                self._interrupted(now, "link loss", f"the board reports setpoints {_kpa(setpoints_pa)} kPa since its "
                                  f"link was lost, not the target's {_kpa(away.held_pa)} kPa")
            else:
                away.frames_seen = True
        if self.fault_names or self.busy or not self.watch.frame(setpoints_pa, now):
            return
        expected = self.watch.expected_pa
        self.watch.expect(None, now)  # once: the vent sets what is expected next
        text = (f"the board holds setpoints {_kpa(setpoints_pa)} kPa that the daemon did not send (it sent "
                f"{_kpa(expected)} kPa): another program is driving the board (a process on its port?) or the "
                "board lost its state; the phantom is vented and the target dropped: find what drove it, then "
                "set a target again")
        self._tell("board", text, "ERROR")
        self.vent(now, text, "ERROR")
        self._actions.append(ConfigureBoard("after the mismatch"))

    def measured(self, now: float, pressures_pa: np.ndarray) -> None:
        """The measured pressures, averaged over the estimate's window (Pa)."""
        self._measured = (now, np.asarray(pressures_pa, dtype=float))
        self._reach_tick(now)

    def estimated(self, now: float, gland_ml: float, chamber_ml: tuple[float, ...] | None) -> None:
        """An estimate of pressures measured at ``now`` or later."""
        for reach in (self._reach, self._again):
            if reach is not None and now >= reach.applied_s:
                reach.estimate = (gland_ml, chamber_ml)
        self._reach_tick(now)

    def model_changed(self, now: float) -> None:
        """The model answers on another level: the target is solved again on it and its setpoints sent."""
        if self.target is not None and self.state is not ControlState.VENTED:
            self.answer, self.applied = None, None
        self._next(now)

    def scanned(self, now: float, round_: int, volume_ml: float | None, error: str | None = None,
                folder: str | None = None, true_ml: float | None = None, link_lost: bool = False,
                hull_error_pct: float | None = None) -> None:
        """The scan of a verified target's round ``round_``: the reconstructed gland volume (ml), or ``error``;
        ``true_ml``, the simulated phantom's true volume at the scan (None on a real board), goes in the round.
        ``link_lost``: the board's link was lost during a scan that failed (or just before it); it is taken again
        (at most :data:`~phantom.host.verify.SCAN_RETRIES` times) once the pressures, applied again, have settled.
        ``hull_error_pct``: the visual hull's error on the model's shape (%), taken off the volume (the round then
        stops within more of the tolerance, :func:`phantom.host.verify.aim_share`; None: not taken off). What the
        scan means is the verify policy's (:meth:`phantom.host.verify.Rounds.scanned`); the core tells it."""
        rounds, reach = self._rounds, self._reach
        if rounds is None or reach is None:
            return  # the verification ended meanwhile (a fault, a vent, another target): its scan is not used
        judged = rounds.scanned(round_, volume_ml, error, folder, true_ml, link_lost, hull_error_pct)
        described = reach.target.describe()
        if judged == "stale":
            return
        if judged == "retry":
            self._tell("verify", f"target {described}: the scan of round {round_} failed while the board's link was "
                       f"lost ({error}): scanned again once the pressures have settled (retry {rounds.retries} of "
                       f"{SCAN_RETRIES})", "WARN")
            return
        if judged == "failed":
            self._outcome("scan_failed", f"target {described} not verified: the scan of round {round_} failed "
                          f"({rounds.last['scan_error']}); no correction was made from it and the pressures are "
                          "held", "ERROR", extra=rounds.to_json())
            return
        assert volume_ml is not None
        verify, error_pct = rounds.verify, rounds.last["scanned_error_pct"]
        within = abs(error_pct) <= verify.tolerance_pct
        if judged == "verified":
            self._actions.append(rounds.record())
            self._verified_outcome(reach, rounds, f"target {described} reached and MEASURED: scanned "
                                   f"{volume_ml:.2f} ml ({error_pct:+.2f} %, {'within' if within else 'outside'} "
                                   f"{verify.tolerance_pct:g} %) after {round_} round(s)")
        elif judged == "not_verified":
            self._actions.append(rounds.record())
            self._outcome("not_verified", f"target {described} not verified: scanned {volume_ml:.2f} ml "
                          f"({error_pct:+.2f} %) after {round_} round(s), the limit; the pressures are held (give "
                          "more verify_rounds, or a wider verify_tolerance_pct)", "WARN", extra=rounds.to_json())
        else:
            setpoints = tuple(float(p) for p in self.setpoints_pa) if self.setpoints_pa is not None else ()
            aim_pct = rounds.last["aim_pct"]
            outside = (f"within {verify.tolerance_pct:g} % but outside the {aim_pct:.2g} % aimed at" if within
                       else f"outside {verify.tolerance_pct:g} %")
            self._tell("verify", f"target {described}: round {round_} scanned {volume_ml:.2f} ml ({error_pct:+.2f} "
                       f"%, {outside}): correcting")
            self._actions.append(rounds.correct(reach.target, setpoints))

    def corrected(self, now: float, round_: int, answer: InverseResult, how: str) -> None:
        """The pressures of the round after ``round_`` (``how`` says what they were solved for): applied."""
        rounds = self._rounds
        if rounds is None or self._reach is None or not rounds.corrected(round_, answer, how):
            return
        self.answer = answer
        self.applied = None
        self._next(now)

    def confirmed(self, now: float, round_: int, corrected_ml: float, band_ml: float) -> None:
        """Round ``round_``'s scan, within the tolerance but off the aim, is confirmed by the correction refitted
        with it (:func:`phantom.host.verify.confirmed_by_correction`): reached and MEASURED, no next round (the
        scan is stored already)."""
        rounds, reach = self._rounds, self._reach
        if rounds is None or reach is None or not rounds.confirmed(round_, corrected_ml, band_ml):
            return
        last, target_ml = rounds.last, rounds.target_ml
        self._verified_outcome(reach, rounds, f"target {reach.target.describe()} reached and MEASURED: scanned "
                               f"{last['scanned_volume_ml']:.2f} ml ({last['scanned_error_pct']:+.2f} %, within "
                               f"{rounds.verify.tolerance_pct:g} %) after {round_} round(s), and the correction "
                               f"refitted with the scan says {corrected_ml:.2f} ml +-{band_ml:.3f} ml (95 %) there "
                               f"({100.0 * (corrected_ml - target_ml) / target_ml:+.2f} % +-"
                               f"{100.0 * band_ml / target_ml:.2f} %), within it too")

    def held(self, now: float, round_: int, next_kpa: tuple[float, ...]) -> None:
        """Round ``round_``'s scan is within the tolerance and the next round's pressures ``next_kpa`` are a step
        the board cannot hold (:func:`phantom.host.verify.beyond_the_boards_step`): reached and MEASURED, no next
        round (the scan is stored already)."""
        rounds, reach = self._rounds, self._reach
        if rounds is None or reach is None or not rounds.held(round_, next_kpa):
            return
        last = rounds.last
        self._verified_outcome(reach, rounds, f"target {reach.target.describe()} reached and MEASURED: scanned "
                               f"{last['scanned_volume_ml']:.2f} ml ({last['scanned_error_pct']:+.2f} %, within "
                               f"{rounds.verify.tolerance_pct:g} %) after {round_} round(s); the next round's "
                               f"pressures are within one ADC count of these near rest, a step the board cannot "
                               "hold, so the scan stands")

    def correct_failed(self, now: float, round_: int, unreachable: bool, text: str) -> None:
        """The next round's pressures could not be solved (``unreachable``, or the model failed): the pressures
        of the last round are held."""
        rounds, reach = self._rounds, self._reach
        if rounds is None or reach is None or not rounds.correcting(round_):
            return
        self._outcome("unreachable" if unreachable else "not_verified",
                      f"target {reach.target.describe()} not verified: the correction after round {round_} failed "
                      f"({text}); the pressures are held", "WARN", extra=rounds.to_json())

    def scene_started(self, now: float) -> None:
        self.state = ControlState.SCENE
        self._drop_offer("replaced by a scene before it was sent")

    def scene_ended(self, now: float, why: str, stop: bool = False) -> None:
        """The scene finished (its last target holds) or, with ``stop``, is stopped (``why``)."""
        if self.state is ControlState.SCENE:
            self.state = ControlState.HOLDING
            if stop:
                self._actions.append(StopScene(why))

    def tick(self, now: float) -> None:
        """What is due: a retry, a target to apply, what waits, reached."""
        self._next(now)
        self._reach_tick(now)

    # --- the rules ----------------------------------------------------------------------------------------

    def _why_not_now(self) -> str | None:
        if not self.board_ready:
            return self.board_why
        if self.fault_names:
            return f"faults latched on the board ({', '.join(self.fault_names)}): clear them (phantom clear-fault)"
        if self.zeroing_why is not None:
            return f"the sensors are being zeroed: {self.zeroing_why}"
        return None

    def _next(self, now: float) -> None:
        """The one place that decides the next command to the board, or the next solve."""
        if self.busy:
            return
        if self._vent is not None:
            if self._vent_waits_for_board:
                return
            self._venting = True
            self.watch.expect(None, now)  # in flight: the board may show either
            self._actions.append(self._vent)
            return
        offer = self._offer
        if offer is not None:
            self._offer, self._offer_sent = None, offer
            self._send(now, offer.answer.target, offer.answer)
            return
        target = self.target
        if target is None or self.state is ControlState.VENTED or self.applied == target:
            return
        why = self._why_not_now()
        if why is not None:
            self._wait(why)
            return
        if now < self._retry_after_s or target == self._unreachable or self._solving is not None:
            return
        self._retry_after_s = -np.inf  # due: tried now
        answer = self.answer
        if answer is not None and (answer.target == target or (self._rounds is not None
                                                                and answer is self._rounds.answer)):
            self._send(now, target, answer)
        else:
            self._solving = target
            self._actions.append(Solve(target, self.ramp))

    def _send(self, now: float, target: Target, answer: InverseResult) -> None:
        self._sending = SendSetpoints(target, setpoints_for(answer.pressures_pa))
        self.watch.expect(None, now)  # in flight: the board may show either
        self._actions.append(self._sending)

    def _drop_offer(self, why: str) -> None:
        if self._offer is not None:
            self._actions.append(Answer(self._offer.request, error=("replaced", why)))
        self._offer = None

    def _set_target(self, now: float, target: Target, source: str, step: int | None,
                    ramp: tuple[Target, Target] | None, tolerance_pct: float | None) -> None:
        if target != self.target or source != self.source:
            self._replaced(f"replaced by {target.describe()} ({source})")
            self._forget_reached()
        if self._pending_since_s is None:
            self._pending_since_s = now
        if self.answer is not None and self.answer.target != target:
            self.answer = None
        self.target, self.source, self.step, self.ramp = target, source, step, ramp
        self.tolerance_pct = tolerance_pct
        self._retry_after_s = -np.inf

    def _applied(self, now: float, target: Target) -> None:
        waited = self.pending
        self.pending, self._unreachable, self._retry_after_s = None, None, -np.inf
        if self.step is not None:
            self._actions.append(StepApplied(self.step))
        if waited is not None and self._pending_since_s is not None:
            self._tell("target", f"target {target.describe()} applied after {now - self._pending_since_s:.1f} s "
                       f"(it waited: {waited})")
        self._pending_since_s = None
        self._start_reach(now)

    def _start_reach(self, now: float) -> None:
        """Judge reached from now on (a scene's ramp points are not waited on: its step is, once the ramp ends)."""
        target = self.target
        if target is not None and target == self._reached and self._held in ("not_held", "settling"):
            # reached before an interruption: its setpoints, sent again, are judged until held again (told once)
            self._held = "settling"
            if self._again is not None and self._again.target == target:
                self._again.again(now, self.rule)
            else:
                self._again = _Reach(target, self.source or "", self.step, self.tolerance_pct
                                     or self.rule.tolerance_pct, now, Settling(self.rule))
            return
        if target is None or self.ramp is not None or target == self._reached:
            return
        if self._reach is not None and self._reach.target == target:
            self._reach.again(now, self.rule)
            return
        self._reach = _Reach(target, self.source or "", self.step, self.tolerance_pct or self.rule.tolerance_pct, now,
                             Settling(self.rule))

    def _wait(self, why: str) -> None:
        """The target waits: said once per reason."""
        if why != self.pending and self.target is not None:
            self._tell("target", f"target {self.target.describe()} not applied: {why}"
                       + ("" if why.startswith("unreachable") else "; it will be applied as soon as the board can "
                          "take it"), "WARN")
        self.pending = why

    def _settled_s(self, reach: _Reach, now: float) -> float | None:
        """How long (s) the pressures have been within the rule's band of the setpoints held for ``reach``'s
        target, once that is long enough and there is an estimate to judge; None before."""
        if (reach.target != self.applied or not self.board_ready or self.fault_names or self._measured is None
                or self.setpoints_pa is None):
            return None
        measured_s, measured_pa = self._measured
        if measured_s < reach.applied_s:
            return None
        reach.settling.frame(measured_s, measured_pa, self.setpoints_pa)
        since_s = reach.settling.since_s
        settled_s = 0.0 if since_s is None else now - since_s
        if settled_s < self.rule.settled_for_s or reach.estimate is None:
            return None
        return settled_s

    def _reach_tick(self, now: float) -> None:
        """Reached: the one definition (:class:`ReachRule`). A scan's verified target adds its check after it."""
        self._held_again_tick(now)
        reach = self._reach
        settled_s = None if reach is None else self._settled_s(reach, now)
        if reach is None or settled_s is None or reach.estimate is None or self._measured is None:
            return
        measured_pa = self._measured[1]
        assert self.setpoints_pa is not None  # (judged on them)
        gland_ml, chamber_ml = reach.estimate
        rounds = self._rounds
        if rounds is None:
            if not estimate_within(reach.target, self.answer, gland_ml, chamber_ml, reach.tolerance_pct):
                return
        elif self.answer is not None:
            # a scan carves the intersection of its pictures: one taken before the phantom came to its volume
            # would trim the hull, so the estimate must have come to the round's own answer (its pressures are
            # solved for a corrected model or a shifted volume) within the verify tolerance first
            wanted_ml = predicted_volume_ml(self.answer)
            if abs(gland_ml - wanted_ml) > min(reach.tolerance_pct, rounds.verify.tolerance_pct) / 100.0 * wanted_ml:
                return
        pressures_kpa = [float(p) / PA_PER_KPA for p in measured_pa]
        extra: dict[str, Any] = {"estimated_volume_ml": gland_ml,
                                 "estimated_chamber_volumes_ml": list(chamber_ml) if chamber_ml is not None else None,
                 "measured_pressures_kpa": pressures_kpa, "after_s": now - reach.applied_s}
        if rounds is not None:
            if rounds.doing is None:
                setpoints_kpa = [float(p) / PA_PER_KPA for p in self.setpoints_pa]
                scan = rounds.scan(reach.target, None if self.answer is None else self.answer.band_ml,
                                   setpoints_kpa, pressures_kpa, extra)
                self._tell("verify", f"target {reach.target.describe()}: round {scan.round} settled "
                           f"(estimate {gland_ml:.2f} ml): scanning")
                self._actions.append(scan)
            return
        text = f"target {reach.target.describe()} reached: estimate {gland_ml:.2f} ml, pressures settled for " \
               f"{settled_s:.1f} s"
        if self._sure is not None:  # verify = "auto" with a band within the tolerance: no scan
            verify, answer = self._sure
            band_pct = 100.0 * (answer.band_ml or 0.0) / gland_ml
            text += (f"; verify auto: within +-{band_pct:.2f} % (95 %) from {answer.measurements} stored "
                     f"measurement(s), within the {verify.tolerance_pct:g} % asked, so not scanned")
            extra |= {"verify": verify.to_json(), "verified": False, "scanned": False, "band_ml": answer.band_ml,
                      "band_pct": band_pct, "measurements": answer.measurements}
        self._reached_now(reach, "reached", text, extra)

    def _held_again_tick(self, now: float) -> None:
        """A reached target's setpoints, sent again after an interruption, held again by the same rule: told once,
        as an event without an outcome (its outcome was told: reached)."""
        again = self._again
        settled_s = None if again is None else self._settled_s(again, now)
        if again is None or settled_s is None or again.estimate is None or self._measured is None:
            return
        gland_ml, chamber_ml = again.estimate
        if not self._reached_scanned and not estimate_within(again.target, self.answer, gland_ml, chamber_ml,
                                                             again.tolerance_pct):
            return
        self._again, self._held = None, "held_again"
        after = self._held_after or "fault"
        self._tell("target", f"target {again.target.describe()} held again after {AFTER_WORDS[after]}: estimate "
                   f"{gland_ml:.2f} ml, pressures settled for {settled_s:.1f} s",
                   data={"held_again": True, "after": after, "target": again.target.to_json(), "source": again.source,
                         "estimated_volume_ml": gland_ml,
                         "estimated_chamber_volumes_ml": list(chamber_ml) if chamber_ml is not None else None,
                         "measured_pressures_kpa": [float(p) / PA_PER_KPA for p in self._measured[1]],
                         "after_s": now - again.applied_s})

    def _forget_reached(self) -> None:
        """The target is judged afresh (another one, the same asked again, a vent): its reached and what came of
        it after an interruption go."""
        self._reached, self._reached_scanned, self._again, self._away = None, False, None, None
        self._held = self._held_after = None

    def _holds_reached(self) -> bool:
        """Whether the target in force was told reached (and not vented since)."""
        return self.target is not None and self.target == self._reached and self.state is not ControlState.VENTED

    def _went_away(self) -> None:
        """The board can no longer take setpoints (its link lost, or being set up again): a reached target whose
        setpoints it held may have lost them, which its first frame back says (a board away again before that
        is judged afresh)."""
        if self._away is not None:
            self._away.frames_seen, self._away.acked_s = False, None
        elif (self._holds_reached() and self.applied == self.target and self.setpoints_pa is not None
              and self._held != "not_held"):
            self._away = _Away(np.array(self.setpoints_pa, dtype=float))

    def _interrupted(self, now: float, after: str, why: str) -> None:
        """The board lost the setpoints of the reached target (``after`` what, ``why`` in words): it is not held
        until they are acknowledged again, then judged until held again. Said once (a fault says it itself)."""
        self._away = None
        if not self._holds_reached():
            return
        said = self._held == "not_held"
        self._held, self._held_after, self._again = "not_held", after, None
        if not said and after != "fault":
            assert self.target is not None
            self._tell("target", f"target {self.target.describe()} not held: {why}; its setpoints go to the board "
                       "again, and it is told when they are held again", "WARN")

    def _reached_now(self, reach: _Reach, outcome: str, text: str, extra: dict[str, Any]) -> None:
        if reach.step is not None:
            self._actions.append(StepReached(reach.step))
        self._reached, self._reached_scanned = reach.target, extra.get("scanned_volume_ml") is not None
        self._held = self._held_after = self._again = self._away = None
        self._outcome(outcome, text, extra=extra)

    def _verified_outcome(self, reach: _Reach, rounds: Rounds, text: str) -> None:
        """Reached, the volume reported the scanned one (measured), with the rounds."""
        last = rounds.rounds[-1]
        extra = {"estimated_volume_ml": last["estimated_volume_ml"],
                 "estimated_chamber_volumes_ml": last["estimated_chamber_volumes_ml"],
                 "measured_pressures_kpa": last["pressures_kpa"], "after_s": last["after_s"],
                 **rounds.to_json()}
        self._reached_now(reach, "reached", text, extra)

    def _replaced(self, why: str) -> None:
        if self._reach is not None:
            self._outcome("replaced", f"target {self._reach.target.describe()} not reached: {why}")

    def _outcome(self, outcome: str, text: str, level: str = "INFO", extra: dict[str, Any] | None = None) -> None:
        """An outcome of the target waited on (reached, replaced, unreachable, faulted): told once, with data."""
        reach, self._reach = self._reach, None
        verifying = self._rounds is not None
        if self._rounds is not None and self._rounds.doing == "scanning":
            self._actions.append(StopScan(f"its verification ended: {text}"))
        self._rounds = self._sure = None  # a verification ends with its target's outcome
        target = reach.target if reach is not None else self.target
        if target is None:
            return
        source = reach.source if reach is not None else self.source
        self._tell("target", text, level, {"outcome": outcome, "target": target.to_json(), "source": source,
                                           **(extra or {})}, after_stored=verifying)

    def _tell(self, kind: str, text: str, level: str = "INFO", data: dict[str, Any] | None = None,
              after_stored: bool = False) -> None:
        self._actions.append(Tell(kind, text, level, data, after_stored))


def _differ(setpoints_pa: np.ndarray, held_pa: np.ndarray) -> bool:
    """Whether a frame's setpoints are not those held (by more than the wire's pascal)."""
    return bool(np.max(np.abs(np.asarray(setpoints_pa, dtype=float) - held_pa)) > SAME_SETPOINT_PA)


def _kpa(pressures_pa: np.ndarray | None) -> str:
    """Pressures (Pa) as people read them: ``1.000, 0.500, 0.000`` (kPa)."""
    return "none" if pressures_pa is None else ", ".join(f"{p / PA_PER_KPA:.3f}" for p in pressures_pa)
