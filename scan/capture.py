"""Capture: turn the orbit, let it settle, take a picture at each stop, and keep everything in a capture folder.

The capture loop (:func:`capture`) drives three things it is given, each typed by a Protocol so that the loop
imports nothing of the daemon or the simulator: an :class:`Orbit` (move to an orbit angle and an elevation and
say where it stopped; release the motors), a :class:`FrameSource` (a webcam through OpenCV's ``VideoCapture``, or
the virtual camera) and a :class:`PhantomState` (the chamber pressures now; it raises when the phantom cannot be
scanned: a latched fault, a lost link). On a fault, a lost camera or Ctrl-C the loop stops the orbit with its
motors released, marks the folder ``aborted`` with the reason, and keeps the pictures taken. A
:class:`StopFlag` (the daemon's scan: ``motion_stop``, SIGTERM) is checked before each move, during the settle
wait and after each picture: the loop then releases the motors and marks the folder ``stopped``.

A capture folder, readable by any tool::

    capture.json        {"format": "phantom-capture/1",
                         "status": "running" | "complete" | "aborted" | "stopped",
                         "reason", "started_utc", "finished_utc", "camera": {...}, "plan": {...},
                         "conditions": {...}, "rig": "rig.json" or null,
                         "frames": [{"index", "image", "orbit_deg", "elevation_deg", "pressures_kpa",
                                     "time_utc", "time_s"}, ...]}
    rig.json            the rig's calibration (phantom.scan.camera.Rig), when one is known
    images/0000.png     the pictures, 8-bit sRGB, in the order taken

``orbit_deg`` and ``elevation_deg`` are the angles the rig reported when the picture was taken (read just
before and just after it, the mean of the two), not the planned ones: a frame whose reported angles differ from
the plan's by more than MAX_ANGLE_ERROR_DEG (the rig moved by someone else, or still moving) is refused and the
capture aborted, rather than recorded at a wrong angle. ``time_s`` is seconds since the capture started
(``time_utc`` the wall clock); capture.json is rewritten (atomically) after every picture, so an aborted or
stopped capture is readable too.
"""

from __future__ import annotations

import atexit
import concurrent.futures
import contextlib
import datetime
import json
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from phantom import PhantomError, is_finite_number, require_extra
from phantom.protocol.motion import AxisConfig
from phantom.scan.camera import MAX_PICTURE_SIDE_PX, Rig, checked_array

CAPTURE_FORMAT = "phantom-capture/1"
CAPTURE_FILE = "capture.json"
RIG_FILE = "rig.json"
IMAGES = "images"
#: The most pictures a capture folder may hold (360 per turn in five passes is 1800): each is carved with, and
#: a capture.json naming more is not ours.
MAX_FRAMES = 2000
#: The largest orbit and elevation angles (deg) a frame may have: the orbit's soft limits are +-190 deg.
MAX_FRAME_ANGLE_DEG = 360.0
#: How far (deg) the angles the rig reports at a picture may be from the plan's: eight of the orbit's steps
#: (80 a degree), 0.04 mm at the gland's surface 25 mm from the axis, far below a voxel; a rig that is further off
#: was moved by someone else or is still moving.
MAX_ANGLE_ERROR_DEG = 0.1


class CaptureError(PhantomError):
    """A capture that stopped (the reason and where the pictures taken are kept), or a capture folder that
    cannot be read."""


class CaptureStopped(CaptureError):
    """A capture stopped on request (``motion_stop``, the daemon stopping): the folder is marked ``stopped``."""


class CameraLost(PhantomError):
    """The camera gave no picture (unplugged, closed, the end of a recording)."""


class Orbit(Protocol):
    """The scanner's axes as the capture needs them."""

    def move_to(self, orbit_deg: float, elevation_deg: float) -> tuple[float, float]:
        """Move both axes there and wait until they are at rest; return the angles reached (deg)."""

    def position_deg(self) -> tuple[float, float]:
        """Where the axes are now (deg), as the rig reports them (on the simulated board its true angles)."""

    def release(self) -> None:
        """Stop any motion and release the motors' drivers."""


class StopFlag(Protocol):
    """A request to stop the capture from another thread (``phantom.host.motion.ThreadRig``)."""

    def stop_requested(self, wait_s: float = 0.0) -> str | None:
        """Why the capture must stop, or None to go on; waits up to ``wait_s`` for a request (the settle wait)."""


class FrameSource(Protocol):
    """A camera. One that renders its pictures (the virtual camera) also has ``take() -> Callable[[],
    np.ndarray]``: the picture's moment now (its scene and angles read), its rendering when called, which the
    capture loop does while the rig moves to the next stop (:func:`capture`)."""

    def grab(self) -> np.ndarray:
        """A picture taken now: 8-bit RGB (height, width, 3); CameraLost if there is none."""

    def describe(self) -> dict[str, Any]:
        """What the camera is and how it is set, for capture.json."""

    def close(self) -> None:
        """Lets the camera go (a webcam's device, a stream's reader); one that holds nothing does nothing."""


class PhantomState(Protocol):
    """The phantom being scanned."""

    def pressures_kpa(self) -> list[float] | None:
        """The chamber pressures now (kPa), None if unknown; raises PhantomError when the phantom cannot be
        scanned (a latched fault, the board's link lost)."""


#: The most orbit stops per elevation (0.5 deg apart on a whole turn): beyond it the pictures overlap and a scan
#: only grows the daemon's memory and time.
MAX_VIEWS = 720
#: The most elevations (passes) of one plan.
MAX_ELEVATIONS = 8
#: The longest wait after a move (s): a rig that needs longer to stop swinging needs fixing, not waiting, and a
#: longer wait holds the rig (and the scan's lock) for hours on a whole plan.
MAX_SETTLE_S = 10.0
#: The angles a plan may name (deg): the orbit's start and the elevations; the board's soft limits refuse the
#: moves the mechanism cannot make.
MAX_ANGLE_DEG = 360.0


def _finite(name: str, value: object, low: float, high: float, unit: str, why: str) -> float:
    """``value`` as a float within [low, high], or CaptureError saying which parameter and why."""
    if not is_finite_number(value):
        raise CaptureError(f"{name} must be a finite number of {unit}, got {value!r}")
    if not low <= value <= high:
        raise CaptureError(f"{name} must be between {low:g} and {high:g} {unit} ({why}), got {value:g}")
    return float(value)


@dataclass(frozen=True)
class Plan:
    """Where to take pictures: ``views`` orbit stops per elevation from ``start_deg``, evenly over a whole turn
    (``span_deg`` 360, the last stop one step short of the first) or over ``span_deg`` (both ends included), at
    each elevation (deg) in order; ``settle_s`` after each move before the picture.

    Every parameter is checked when the plan is made (CaptureError says which and why), before any move: a
    NaN or negative wait, a million views or a wait of days are refused, not started."""

    views: int
    elevations_deg: tuple[float, ...] = (0.0, 30.0)
    #: a whole turn from -180 deg stays within the orbit's soft limits (+-190 deg: its cable allows little more)
    start_deg: float = -180.0
    settle_s: float = 0.3
    span_deg: float = 360.0

    def __post_init__(self) -> None:
        if isinstance(self.views, bool) or not isinstance(self.views, int):
            raise CaptureError(f"views must be a whole number from 1 to {MAX_VIEWS}, got {self.views!r}")
        if self.views < 1:
            raise CaptureError(f"views must be at least 1 (a capture needs at least one view), got {self.views}")
        if self.views > MAX_VIEWS:
            raise CaptureError(f"views must be at most {MAX_VIEWS} per elevation (0.5 deg apart on a turn), got "
                               f"{self.views}")
        if not 1 <= len(self.elevations_deg) <= MAX_ELEVATIONS:
            raise CaptureError(f"a capture needs one to {MAX_ELEVATIONS} elevations, got "
                               f"{list(self.elevations_deg)}")
        for elevation in self.elevations_deg:
            _finite("an elevation", elevation, -90.0, 90.0, "deg", "the camera's arc")
        pictures = self.views * len(self.elevations_deg)
        if pictures > MAX_FRAMES:
            raise CaptureError(f"views {self.views} at {len(self.elevations_deg)} elevation(s) is {pictures} pictures: "
                               f"give from 1 to {MAX_FRAMES} in all")
        _finite("start_deg", self.start_deg, -MAX_ANGLE_DEG, MAX_ANGLE_DEG, "deg", "one turn either way")
        _finite("span_deg", self.span_deg, 0.0, 360.0, "deg", "at most a whole turn")
        if self.span_deg == 0:
            raise CaptureError("span_deg must be above 0 deg (360: a whole turn), got 0")
        _finite("settle_s", self.settle_s, 0.0, MAX_SETTLE_S, "s", "the wait after each move")

    def stops(self) -> list[tuple[float, float]]:
        """The (orbit, elevation) stops in the order taken: every other pass runs backwards, so the orbit never
        travels back a whole turn between passes."""
        if self.span_deg >= 360.0:
            angles = [self.start_deg + 360.0 * k / self.views for k in range(self.views)]
        else:
            angles = [self.start_deg + self.span_deg * k / max(self.views - 1, 1) for k in range(self.views)]
        stops = []
        for number, elevation in enumerate(self.elevations_deg):
            stops += [(angle, elevation) for angle in (angles if number % 2 == 0 else angles[::-1])]
        return stops

    def moves_s(self, axes: Sequence[AxisConfig]) -> float:
        """The board's time (s) for this plan's moves on ``axes`` (the orbit's configuration, the elevation's), as
        the daemon moves them (each stop's elevation, then its orbit), and from the last stop to where the next
        scan of the plan starts: the daemon takes it from the elevation this one ended at, its passes the other way
        round (``phantom.host.verify.passes_from``), so after an even number of passes it starts where this one
        ended, after an odd number a turn back."""
        orbit, elevation = axes
        stops = self.stops()
        following = replace(self, elevations_deg=self.elevations_deg[::-1]).stops()[0]
        return sum(elevation.move_s(to[1] - at[1]) + orbit.move_s(to[0] - at[0])
                   for at, to in zip(stops, [*stops[1:], following], strict=True))

    def board_s(self, axes: Sequence[AxisConfig]) -> float:
        """The plan's time on the board (s): its moves on ``axes`` (:meth:`moves_s`) and its settle after each
        stop."""
        return self.moves_s(axes) + self.settle_s * len(self.stops())

    def to_json(self) -> dict[str, Any]:
        return {"views_per_elevation": self.views, "elevations_deg": list(self.elevations_deg),
                "start_deg": self.start_deg, "span_deg": self.span_deg, "settle_s": self.settle_s}


@dataclass
class Frame:
    """One picture's record in capture.json."""

    index: int
    image: str
    orbit_deg: float
    elevation_deg: float
    pressures_kpa: list[float] | None
    time_utc: str
    time_s: float
    #: where the picture's time went (s), by stage of the capture loop (:data:`STAGES`); None when not measured
    stage_s: dict[str, float] | None = None


#: The capture loop's stages, as each picture's ``stage_s`` names them: the move to the stop (``move``: the board's
#: move and its acknowledgements), the settle wait and stop check (``settle``), the pressures read (``pressures``),
#: the rig's angles read before and after the picture (``position``), the picture taken or rendered (``grab``),
#: written with its record (``write``) and, for a capture that keeps its pictures' silhouettes, keyed (``key``).
STAGES = ("move", "settle", "pressures", "position", "grab", "write", "key")


@dataclass
class CaptureFolder:
    """A capture folder (see the module docstring)."""

    path: Path
    camera: dict[str, Any]
    plan: dict[str, Any]
    conditions: dict[str, Any] = field(default_factory=dict)
    frames: list[Frame] = field(default_factory=list)
    status: str = "running"
    reason: str | None = None
    started_utc: str = ""
    finished_utc: str | None = None
    rig_file: str | None = None

    @classmethod
    def create(cls, path: str | Path, camera: dict[str, Any], plan: dict[str, Any],
               conditions: dict[str, Any] | None = None, rig: Rig | None = None) -> CaptureFolder:
        """A new, empty capture folder (CaptureError if it holds a capture already)."""
        path = Path(path)
        if (path / CAPTURE_FILE).exists():
            raise CaptureError(f"{path} already holds a capture: give another --out folder")
        try:
            (path / IMAGES).mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise CaptureError(f"cannot make the capture folder {path}: {error.strerror or error}") from None
        folder = cls(path, camera, plan, dict(conditions or {}), started_utc=_utc_now())
        if rig is not None:
            rig.save(path / RIG_FILE)
            folder.rig_file = RIG_FILE
        folder.write()
        return folder

    def add(self, image: np.ndarray, orbit_deg: float, elevation_deg: float, pressures_kpa: list[float] | None,
            time_s: float) -> Frame:
        """Write one picture (RGB) and its record."""
        with require_extra("scan"):
            import cv2

        index = len(self.frames)
        name = f"{IMAGES}/{index:04d}.png"
        if not cv2.imwrite(str(self.path / name), np.ascontiguousarray(image[:, :, ::-1])):
            raise CaptureError(f"cannot write {self.path / name}: is the disk full?")
        frame = Frame(index, name, float(orbit_deg), float(elevation_deg),
                      None if pressures_kpa is None else [float(p) for p in pressures_kpa], _utc_now(), float(time_s))
        self.frames.append(frame)
        self.write()
        return frame

    def finish(self, status: str, reason: str | None = None) -> None:
        self.status, self.reason, self.finished_utc = status, reason, _utc_now()
        self.write()

    def to_json(self) -> dict[str, Any]:
        return {"format": CAPTURE_FORMAT, "status": self.status, "reason": self.reason,
                "started_utc": self.started_utc, "finished_utc": self.finished_utc, "camera": self.camera,
                "plan": self.plan, "conditions": self.conditions, "rig": self.rig_file,
                "frames": [asdict(frame) for frame in self.frames]}

    def write(self) -> None:
        """capture.json, replaced atomically (a reader never sees half of it)."""
        temporary = self.path / (CAPTURE_FILE + ".new")
        try:
            temporary.write_text(json.dumps(self.to_json(), indent=1) + "\n")
            os.replace(temporary, self.path / CAPTURE_FILE)
        except OSError as error:
            raise CaptureError(f"cannot write {self.path / CAPTURE_FILE}: {error.strerror or error}") from None

    @classmethod
    def open(cls, path: str | Path) -> CaptureFolder:
        """Read a capture folder; CaptureError if it is not one."""
        path = Path(path)
        try:
            data = json.loads((path / CAPTURE_FILE).read_text())
        except FileNotFoundError:
            raise CaptureError(f"{path} is not a capture folder (no {CAPTURE_FILE}): give the folder that phantom "
                               f"scan capture or render wrote") from None
        except (OSError, json.JSONDecodeError) as error:
            raise CaptureError(f"cannot read {path / CAPTURE_FILE}: {error}") from None
        if not isinstance(data, dict) or data.get("format") != CAPTURE_FORMAT:
            raise CaptureError(f"{path / CAPTURE_FILE} is not a {CAPTURE_FORMAT} capture")
        records = data.get("frames")
        if not isinstance(records, list) or len(records) > MAX_FRAMES:
            count = len(records) if isinstance(records, list) else records
            raise CaptureError(f"{path / CAPTURE_FILE}: frames must be a list of at most {MAX_FRAMES} pictures, got "
                               f"{count!r:.80}: that is not a capture of ours")
        frames = [_checked_frame(record, f"{path / CAPTURE_FILE}: frame {number}")
                  for number, record in enumerate(records)]
        images = [frame.image for frame in frames]
        if len(set(images)) != len(images):
            twice = next(image for image in images if images.count(image) > 1)
            raise CaptureError(f"{path / CAPTURE_FILE} names the picture {twice} for more than one frame: each frame "
                               f"is its own picture (a damaged or hand-made capture.json)")
        try:
            return cls(path, dict(data.get("camera", {})), dict(data.get("plan", {})),
                       dict(data.get("conditions", {})), frames, str(data.get("status", "complete")),
                       data.get("reason"), str(data.get("started_utc", "")), data.get("finished_utc"), data.get("rig"))
        except (KeyError, TypeError, ValueError) as error:
            raise CaptureError(f"{path / CAPTURE_FILE} is damaged ({type(error).__name__}: {error})") from None

    def rig(self) -> Rig | None:
        """The rig's calibration kept beside the pictures, if any."""
        return Rig.load(self.path / self.rig_file) if self.rig_file else None

    def image(self, frame: Frame) -> np.ndarray:
        """A picture as 8-bit RGB."""
        with require_extra("scan"):
            import cv2

        if not (self.path / frame.image).is_file():  # said here: OpenCV's reader would print a warning of its own
            raise CaptureError(f"the picture {self.path / frame.image} that {CAPTURE_FILE} names is missing: copy the "
                               f"capture folder whole, or take the capture again")
        width, height = png_size(self.path / frame.image)
        if max(width, height) > MAX_PICTURE_SIDE_PX:
            raise CaptureError(f"{self.path / frame.image} is {width}x{height}, larger than any camera's "
                               f"({MAX_PICTURE_SIDE_PX} px a side): not a picture of this capture")
        picture = cv2.imread(str(self.path / frame.image), cv2.IMREAD_COLOR)
        if picture is None:
            raise CaptureError(f"cannot read the picture {self.path / frame.image}: missing or damaged")
        rgb: np.ndarray = np.ascontiguousarray(picture[:, :, ::-1])
        return rgb


def png_size(path: Path) -> tuple[int, int]:
    """A PNG's width and height (px) from its header, before its pixels are read; (0, 0) for a file that is not
    a PNG (the reader then says what it is)."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(24)
    except OSError:
        return 0, 0
    if len(head) < 24 or not head.startswith(b"\x89PNG\r\n\x1a\n") or head[12:16] != b"IHDR":
        return 0, 0
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _checked_frame(record: Any, where: str) -> Frame:
    """One frame's record of capture.json, checked: finite angles within a turn or two, a picture inside the
    folder, pressures numbers or null; CaptureError naming the field otherwise (a NaN angle was a traceback)."""
    if not isinstance(record, dict):
        raise CaptureError(f"{where} must be an object, got {record!r:.80}")
    image, index = record.get("image"), record.get("index")
    if not isinstance(image, str) or not image or Path(image).is_absolute() or ".." in Path(image).parts:
        raise CaptureError(f"{where}: image must be a picture's path inside the folder, got {image!r:.80}")
    if isinstance(index, bool) or not isinstance(index, int):
        raise CaptureError(f"{where}: index must be a whole number, got {index!r:.80}")
    orbit_deg, elevation_deg = (float(checked_array(record.get(key), (), f"{where}: {key}", CaptureError,
                                                    MAX_FRAME_ANGLE_DEG)) for key in ("orbit_deg", "elevation_deg"))
    pressures = record.get("pressures_kpa")
    if pressures is not None:
        pressures = checked_array(pressures, (len(pressures),) if isinstance(pressures, list) else (-1,),
                                  f"{where}: pressures_kpa", CaptureError).tolist()
    time_s = float(checked_array(record.get("time_s", 0.0), (), f"{where}: time_s", CaptureError))
    stages = record.get("stage_s")
    if stages is not None:
        if not isinstance(stages, dict) or set(stages) - set(STAGES):
            raise CaptureError(f"{where}: stage_s must map some of {', '.join(STAGES)} to seconds, got {stages!r:.80}")
        stages = {name: float(checked_array(value, (), f"{where}: stage_s {name}", CaptureError))
                  for name, value in stages.items()}
    return Frame(index, image, orbit_deg, elevation_deg, pressures, str(record.get("time_utc", "")), time_s, stages)


def _utc_now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")


Progress = Callable[[int, int, Frame], None]


def capture(orbit: Orbit, camera: FrameSource, phantom: PhantomState, plan: Plan, folder: CaptureFolder,
            progress: Progress | None = None, stop: StopFlag | None = None,
            keep: Callable[[Frame, np.ndarray], None] | None = None) -> CaptureFolder:
    """Take the plan's pictures into ``folder``; on any failure or Ctrl-C release the orbit, mark the folder
    aborted (pictures kept) and raise CaptureError (KeyboardInterrupt for Ctrl-C); on a ``stop`` request release
    it, mark the folder stopped and raise CaptureStopped. ``keep`` is given each picture (RGB) once written, in
    the pictures' thread (its time is the picture's ``key`` stage): the daemon's verify scan keys its silhouette
    there (``phantom.scan.keying``)."""
    stops = plan.stops()
    started = time.monotonic()
    pictures = _Pictures(folder, len(stops), progress, keep)
    with _abort_cleanly(orbit, folder, len(stops), stop, pictures.close):
        for orbit_deg, elevation_deg in stops:
            stages = _Stages()
            _check_stop(stop)
            orbit.move_to(orbit_deg, elevation_deg)
            stages.ended("move")
            _check_stop(stop, plan.settle_s)
            stages.ended("settle")
            pressures = phantom.pressures_kpa()
            stages.ended("pressures")
            before = orbit.position_deg()
            stages.ended("position")
            take = getattr(camera, "take", None)
            if take is not None:
                develop = take()
            else:  # a webcam's picture is taken when grabbed
                develop = _as_taken(camera.grab())
            stages.ended("grab")
            after = orbit.position_deg()
            stages.ended("position")
            _check_stop(stop)
            stages.ended("settle")
            reported = _reported_angles((orbit_deg, elevation_deg), before, after, len(folder.frames))
            pictures.add(develop, reported, pressures, time.monotonic() - started, stages.stage_s)
        pictures.close()
        folder.finish("complete")
    return folder


class _Pictures:
    """The pictures developed (a virtual camera's rendered) and written into the folder in a thread of their own,
    one at a time in the order taken, while the rig moves to the next stop (unless a progress callback must see
    each first): a picture's render and PNG then cost the scan nothing but where they are slower than a move.
    The folder's capture.json is written by that thread only while a picture is under way; :meth:`close` waits
    for it before the folder is finished."""

    def __init__(self, folder: CaptureFolder, total: int, progress: Progress | None,
                 keep: Callable[[Frame, np.ndarray], None] | None = None):
        self.folder, self.total, self.progress, self.keep = folder, total, progress, keep
        self._thread = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="capture-pictures")
        self._pending: concurrent.futures.Future[Frame] | None = None

    def add(self, develop: Callable[[], np.ndarray], angles_deg: tuple[float, float], pressures: list[float] | None,
            time_s: float, stage_s: dict[str, float]) -> None:
        """Develop and write a picture (in the thread), once the one before it is written; that one's failure
        (a render's, a full disk) is raised here. With a progress callback the picture is waited for: the
        callback sees each picture before the next move (and may stop the capture there)."""
        self._wait()
        self._pending = self._thread.submit(self._write, develop, angles_deg, pressures, time_s, stage_s)
        if self.progress is not None:
            self._wait()

    def _write(self, develop: Callable[[], np.ndarray], angles_deg: tuple[float, float],
               pressures: list[float] | None, time_s: float, stage_s: dict[str, float]) -> Frame:
        started = time.monotonic()
        picture = develop()
        developed = time.monotonic()
        frame = self.folder.add(picture, *angles_deg, pressures, time_s)
        stage_s["grab"] = round(stage_s.get("grab", 0.0) + developed - started, 4)
        written = time.monotonic()
        stage_s["write"] = round(written - developed, 4)
        if self.keep is not None:
            self.keep(frame, picture)
            stage_s["key"] = round(time.monotonic() - written, 4)
        frame.stage_s = stage_s  # written with the next picture's record, or the folder's end
        return frame

    def _wait(self) -> None:
        pending, self._pending = self._pending, None
        if pending is not None:
            frame = pending.result()
            if self.progress is not None:
                self.progress(len(self.folder.frames), self.total, frame)

    def close(self) -> None:
        """Wait for the picture under way (its failure raised, unless an error is already being handled: the
        picture is then kept if it can be) and end the thread. Idempotent."""
        try:
            self._wait()
        finally:
            self._thread.shutdown()


def _as_taken(picture: np.ndarray) -> Callable[[], np.ndarray]:
    """A picture already developed (a webcam's), as a camera's ``take`` answers."""
    return lambda: picture


class _Stages:
    """A picture's time by stage (s): each :meth:`ended` adds the time since the last to its stage."""

    def __init__(self) -> None:
        self.stage_s: dict[str, float] = {}
        self._last = time.monotonic()

    def ended(self, stage: str) -> dict[str, float]:
        now = time.monotonic()
        self.stage_s[stage] = round(self.stage_s.get(stage, 0.0) + now - self._last, 4)
        self._last = now
        return self.stage_s


def _check_stop(stop: StopFlag | None, wait_s: float = 0.0) -> None:
    """CaptureStopped if a stop is requested now or within ``wait_s`` (which passes otherwise)."""
    if stop is None:
        time.sleep(wait_s)
        return
    reason = stop.stop_requested(wait_s)
    if reason is not None:
        raise CaptureStopped(reason)


def _reported_angles(planned: tuple[float, float], before: tuple[float, float], after: tuple[float, float],
                     index: int) -> tuple[float, float]:
    """The angles to record for a picture: the mean of those the rig reported just before and after it; a
    CaptureError when either is further than MAX_ANGLE_ERROR_DEG from the plan's (the picture is not kept)."""
    for name, axis in (("orbit", 0), ("elevation", 1)):
        off = max(abs(before[axis] - planned[axis]), abs(after[axis] - planned[axis]))
        if not off <= MAX_ANGLE_ERROR_DEG:
            raise CaptureError(f"picture {index}: the rig reported the {name} at {before[axis]:.2f} deg before it "
                               f"and {after[axis]:.2f} deg after it, planned {planned[axis]:.2f} deg (more than "
                               f"{MAX_ANGLE_ERROR_DEG:g} deg off: was the rig moved during the scan?); the picture "
                               f"is not kept")
    return (before[0] + after[0]) / 2, (before[1] + after[1]) / 2


@contextlib.contextmanager
def _abort_cleanly(orbit: Orbit, folder: CaptureFolder, total: int, stop: StopFlag | None,
                   pictures_written: Callable[[], None]) -> Iterator[None]:
    try:
        yield
    except (PhantomError, OSError, KeyboardInterrupt) as error:
        with contextlib.suppress(Exception):  # the picture under way kept if it can be; this error is the one told
            pictures_written()
        # a move that a stop interrupted fails (ended STOPPED): that capture was stopped, not aborted
        requested = stop.stop_requested() if stop is not None else None
        stopped = isinstance(error, CaptureStopped) or requested is not None
        reason = ("interrupted (Ctrl-C)" if isinstance(error, KeyboardInterrupt)
                  else requested if requested is not None else str(error))
        released = _release(orbit)
        folder.finish("stopped" if stopped else "aborted",
                      reason + ("" if released is None else f"; the motors could not be released: {released}"))
        if isinstance(error, KeyboardInterrupt):
            raise
        kind = CaptureStopped if stopped else CaptureError
        raise kind(f"capture {'stopped' if stopped else 'aborted'} after {len(folder.frames)} of {total} pictures: "
                   f"{reason}; the motors are {'released' if released is None else 'NOT released (' + released + ')'}"
                   f" and the pictures taken are kept in {folder.path}") from error
    except BaseException:  # a bug: told as it is, the pictures' thread ended first
        with contextlib.suppress(Exception):
            pictures_written()
        raise


def _release(orbit: Orbit) -> str | None:
    """Release the orbit; the reason it failed, if it did."""
    try:
        orbit.release()
    except (PhantomError, OSError) as error:
        return str(error)
    return None


# --- a webcam ---------------------------------------------------------------------------------------------------


#: A stream's picture is the this-many-th frame to arrive after it was asked for: the first may have been on its
#: way already (sent a frame period before), the second was sent after the ask.
STREAM_FRESH_FRAME = 2
#: A stream that sends no frame for this long (s) is lost: a webcam's 15-30 frames a second, a busy machine's
#: pauses, and a stream's own pauses (the simulated one sends nothing while the rig moves) are all well within.
STREAM_SILENT_S = 10.0
#: A stream whose reads fail this many times in a row is lost. OpenCV's FFmpeg reader decodes a frame as it grabs
#: it, so a frame that cannot be decoded (cut short on a weak link) fails its read and the stream goes on; one that
#: has ended (or timed out) fails every read at once.
STREAM_FAILED_READS = 8


class Webcam:
    """A camera through OpenCV's ``VideoCapture``: a device number (``0``: /dev/video0), or a video file or an
    image sequence (``frames/%04d.png``), which VideoCapture reads through the same API, so a recording can
    stand in for the webcam in a test.

    A network stream (MJPEG over HTTP, RTSP: an IP camera, a phone as a webcam, ``phantom sim-board
    --camera-stream``) is opened by its URL. A device is set to the picture size asked for, with automatic
    exposure, focus and white balance off and ``exposure``/``focus`` fixed when given (in the driver's units);
    what the driver accepted is in :meth:`describe`. Each :meth:`grab` of a device first drops ``flush`` buffered
    frames; a stream is read as it comes, on a thread of its own (:class:`_StreamReader`), and a picture is the
    second frame to arrive after the grab, so it was taken after the orbit stopped, not before; a frame it cannot
    decode is passed over, and a stream whose last :data:`STREAM_FAILED_READS` frames could not be read, or that
    sent nothing for :data:`STREAM_SILENT_S`, is lost (CameraLost). With ``size`` (the rig's calibrated width and
    height), a picture of any other size is refused (CameraLost, saying both).
    """

    def __init__(self, source: int | str, width: int | None = None, height: int | None = None,
                 exposure: float | None = None, focus: float | None = None, flush: int = 4,
                 size: tuple[int, int] | None = None):
        with require_extra("scan"):
            import cv2

        self._cv2 = cv2
        self.source = source
        self.size = size
        # a device and a network stream (a URL) buffer pictures; a recording's every picture is wanted
        self.live = _is_stream(source)
        self.flush = flush if isinstance(source, int) else 0
        self.capture = _open_video(source)
        if not self.capture.isOpened():
            hint = ("is the stream up and its URL right? (open it in a browser)" if self.live
                    else "is it plugged in? (ls /dev/video*)" if isinstance(source, int) else "is the path right?")
            raise CameraLost(f"cannot open the camera {source!r}: {hint}")
        self._stream = _StreamReader(self.capture, source) if self.live else None
        self.settings: dict[str, Any] = {}
        if isinstance(source, int):
            wanted: list[tuple[str, float | None]] = [
                ("CAP_PROP_FRAME_WIDTH", width), ("CAP_PROP_FRAME_HEIGHT", height), ("CAP_PROP_BUFFERSIZE", 1),
                ("CAP_PROP_AUTO_EXPOSURE", 0.25 if exposure is not None else None),  # V4L2: 0.25 = manual
                ("CAP_PROP_EXPOSURE", exposure), ("CAP_PROP_AUTOFOCUS", 0), ("CAP_PROP_FOCUS", focus),
                ("CAP_PROP_AUTO_WB", 0)]
            for name, value in wanted:
                if value is not None:
                    self.settings[name] = {"asked": value,
                                           "accepted": bool(self.capture.set(getattr(cv2, name), value))}

    def grab(self) -> np.ndarray:
        picture: np.ndarray
        if self._stream is not None:
            picture = self._stream.picture()
        else:
            for _ in range(self.flush):
                self.capture.grab()
            ok, picture = self.capture.read()
            if not ok or picture is None:
                raise CameraLost(f"the camera {self.source!r} gave no picture (unplugged, or the recording ended)")
        if picture.ndim == 2:
            picture = self._cv2.cvtColor(picture, self._cv2.COLOR_GRAY2BGR)
        if self.size is not None and (picture.shape[1], picture.shape[0]) != self.size:
            raise CameraLost(f"the camera {self.source!r} gave a {picture.shape[1]}x{picture.shape[0]} picture, the "
                             f"rig was calibrated at {self.size[0]}x{self.size[1]}: nothing of it is kept (has the "
                             f"camera's resolution changed? calibrate the rig at the size it gives)")
        rgb: np.ndarray = np.ascontiguousarray(picture[:, :, ::-1])
        return rgb

    def describe(self) -> dict[str, Any]:
        return {"kind": "webcam", "source": self.source, "settings": self.settings}

    def close(self) -> None:
        if self._stream is not None and not self._stream.stop():
            return  # its reader is still in a read: the capture is left to it (released with the process)
        self.capture.release()


class _StreamReader:
    """A network stream's frames read as they come, on a thread of its own, each decoded and dropped unless a
    picture was asked for; :meth:`picture` answers the :data:`STREAM_FRESH_FRAME`-th frame to arrive after the ask.

    A reader that took the frames only when asked dropped the buffered ones until two in a row made it wait; on a
    machine busy with a process per core two buffered frames, sent before the orbit moved, were each that slow to
    read, and a picture was of the rig where it had been (make test's verified target through the stream: 1-2 of
    a scan's 60 pictures 12 deg behind, the gland read 1.7-2.6 % small, not verified after 4 rounds). Read as they
    come, no frames wait in the buffers when a picture is asked for, and one that arrives after the ask was sent
    after it (a frame period, 33-67 ms, before at worst: the first is skipped for that). The capture is read by
    this thread alone (OpenCV's is not for two threads at once)."""

    def __init__(self, capture: Any, source: int | str):
        self.capture, self.source = capture, source
        self._changed = threading.Condition()
        #: when a picture was asked for (monotonic s), None when none is
        self._asked_s: float | None = None
        self._arrived_since_asked = 0
        self._picture: np.ndarray | None = None
        self._lost: str | None = None
        self._stopping = False
        self._thread = threading.Thread(target=self._read, name=f"camera {source}", daemon=True)
        self._thread.start()
        # a reader left in a read when the interpreter ends aborts the process ("terminate called without an
        # active exception") as its capture is destroyed: one not closed is stopped first
        atexit.register(self.stop)

    def _read(self) -> None:
        failed_reads = 0
        while not self._stopping:
            ok = self.capture.grab()
            arrived_s = time.monotonic()  # before the lock: a picture asked for while it waited is not this frame
            with self._changed:
                if not ok:  # a frame that could not be decoded is passed over for the next; an ended stream is lost
                    failed_reads += 1
                    if failed_reads >= STREAM_FAILED_READS:
                        self._lost = (f"the camera {self.source!r} sent no picture (its last {failed_reads} frames "
                                      f"could not be read: unplugged, the stream ended, or its frames are corrupt)")
                        self._changed.notify_all()
                        return
                    continue
                failed_reads = 0
                if self._asked_s is None or arrived_s < self._asked_s:
                    continue
                self._arrived_since_asked += 1
                if self._arrived_since_asked < STREAM_FRESH_FRAME:
                    continue
                ok, picture = self.capture.retrieve()
                if ok and picture is not None:  # FFmpeg decoded it in its grab; another backend may fail here
                    self._picture, self._asked_s = picture, None
                    self._changed.notify_all()

    def picture(self) -> np.ndarray:
        """The :data:`STREAM_FRESH_FRAME`-th frame to arrive from now (CameraLost when the stream ended, or sent
        nothing for :data:`STREAM_SILENT_S`)."""
        with self._changed:
            self._asked_s, self._arrived_since_asked, self._picture = time.monotonic(), 0, None
            self._changed.wait_for(lambda: self._picture is not None or self._lost is not None, STREAM_SILENT_S)
            self._asked_s = None
            picture, self._picture, lost = self._picture, None, self._lost
        if picture is not None:
            return picture
        raise CameraLost(lost or f"the camera {self.source!r} sent no picture for {STREAM_SILENT_S:.0f} s (is the "
                                 f"stream still up? open its URL in a browser)")

    def stop(self) -> bool:
        """Ends the reading; whether it ended (a read under way on a silent stream ends at the capture's read
        timeout, :data:`STREAM_SILENT_S`)."""
        atexit.unregister(self.stop)
        self._stopping = True
        self._thread.join(STREAM_SILENT_S + 1.0)
        return not self._thread.is_alive()


def _is_stream(source: int | str) -> bool:
    """Whether ``source`` is a network stream's URL (MJPEG over HTTP, RTSP), not a device number or a file."""
    return isinstance(source, str) and "://" in source


def _open_video(source: int | str) -> Any:
    """OpenCV's VideoCapture of ``source`` (a seam for a test to slow its reads)."""
    with require_extra("scan"):
        import cv2

    if _is_stream(source):  # a stream that stops sending ends a read, not waits forever
        return cv2.VideoCapture(source, cv2.CAP_ANY, [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(STREAM_SILENT_S * 1000),
                                                      cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(STREAM_SILENT_S * 1000)])
    return cv2.VideoCapture(source)


def frames_at(folder: CaptureFolder, elevations_deg: Sequence[float] | None = None) -> list[Frame]:
    """The folder's frames, those at the given elevations only when asked."""
    if elevations_deg is None:
        return list(folder.frames)
    return [frame for frame in folder.frames
            if any(abs(frame.elevation_deg - elevation) < 0.05 for elevation in elevations_deg)]
