"""The capture loop's hold on the rig (phantom.scan.capture.capture), one layer with a stand-in orbit: a stop
request is seen before a move, during the settle wait and after a picture (the folder ends "stopped", the motors
released), and every frame is recorded at the angles the rig reported at the picture, a frame the rig was moved
away from being refused. The daemon's side (motion_stop, another client's move, SIGTERM) is tested on the
simulated board in test_scan_rig_sim.py."""

import json
import threading
import time

import numpy as np
import pytest

from phantom import PhantomError
from phantom.scan.capture import MAX_ANGLE_ERROR_DEG, CaptureError, CaptureFolder, CaptureStopped, Plan, capture

pytest.importorskip("cv2")


class StandInOrbit:
    """Where it is told, plus ``offset_deg`` on the orbit from picture ``moved_at`` on (another hand turned it),
    or a move that fails at ``fail_at`` (the board's MOTION_STOP interrupted it)."""

    def __init__(self, offset_deg=0.0, moved_at=None, fail_at=None):
        self.moves, self.released, self.reads = [], 0, 0
        self.offset_deg, self.moved_at, self.fail_at = offset_deg, moved_at, fail_at

    def move_to(self, orbit_deg, elevation_deg):
        if self.fail_at is not None and len(self.moves) == self.fail_at:
            raise PhantomError("the orbit's move to 0 deg ended STOPPED at -97.3 deg")
        self.moves.append((orbit_deg, elevation_deg))
        return orbit_deg, elevation_deg

    def release(self):
        self.released += 1

    def position_deg(self):
        self.reads += 1
        orbit_deg, elevation_deg = self.moves[-1]
        moved = self.moved_at is not None and len(self.moves) > self.moved_at
        return orbit_deg + 0.0125 + (self.offset_deg if moved else 0.0), elevation_deg


class Camera:
    def grab(self):
        return np.full((8, 8, 3), 128, np.uint8)

    def describe(self):
        return {"kind": "test"}


class Phantom:
    def pressures_kpa(self):
        return [1.0, 1.5, 0.5]


class Flag:
    """A stop request as the daemon's scan gives it: set from another thread."""

    def __init__(self):
        self.event, self.reason = threading.Event(), "stopped by motion_stop"

    def stop_requested(self, wait_s=0.0):
        return self.reason if self.event.wait(wait_s) else None


def _folder(tmp_path, plan):
    return CaptureFolder.create(tmp_path / "capture", {"kind": "test"}, plan.to_json())


def _record(tmp_path):
    return json.loads((tmp_path / "capture" / "capture.json").read_text())


def test_a_stop_during_the_settle_wait_ends_the_wait_and_the_capture_stopped(tmp_path):
    """The red team's case: motion_stop during a settle did not stop the scan (the orbit moved on)."""
    plan = Plan(4, (0.0,), settle_s=10.0)
    orbit, flag = StandInOrbit(), Flag()
    threading.Timer(0.3, flag.event.set).start()
    started = time.monotonic()
    with pytest.raises(CaptureStopped, match=r"capture stopped after 0 of 4 pictures: stopped by motion_stop; "
                                             r"the motors are released"):
        capture(orbit, Camera(), Phantom(), plan, _folder(tmp_path, plan), stop=flag)
    assert time.monotonic() - started < 5.0  # not the 10 s settle
    assert orbit.moves == [(-180.0, 0.0)] and orbit.released == 1
    record = _record(tmp_path)
    assert record["status"] == "stopped" and record["reason"] == "stopped by motion_stop" and record["frames"] == []


def test_a_stop_between_pictures_keeps_those_taken_and_moves_no_more(tmp_path):
    plan = Plan(6, (0.0,), settle_s=0.0)
    orbit, flag = StandInOrbit(), Flag()
    taken = []

    def progress(done, total, frame):
        taken.append(done)
        if done == 2:
            flag.event.set()
    with pytest.raises(CaptureStopped, match="after 2 of 6 pictures"):
        capture(orbit, Camera(), Phantom(), plan, _folder(tmp_path, plan), progress, stop=flag)
    assert len(orbit.moves) == 2 and orbit.released == 1 and taken == [1, 2]
    assert _record(tmp_path)["status"] == "stopped" and len(_record(tmp_path)["frames"]) == 2


def test_a_move_that_the_stop_interrupted_ends_the_capture_stopped_not_aborted(tmp_path):
    plan = Plan(4, (0.0,), settle_s=0.0)
    orbit, flag = StandInOrbit(fail_at=1), Flag()
    flag.event.set()  # the stop request came with the board's MOTION_STOP that ended the move
    # picture 0's three questions (before its move, its settle, after it) and picture 1's before its move: go on
    with pytest.raises(CaptureStopped, match="after 1 of 4 pictures: stopped by motion_stop"):
        capture(orbit, Camera(), Phantom(), plan, _folder(tmp_path, plan), stop=_LateFlag(flag, after=4))
    record = _record(tmp_path)
    assert record["status"] == "stopped" and record["reason"] == "stopped by motion_stop" and orbit.released == 1
    assert len(record["frames"]) == 1


class _LateFlag:
    """A flag that answers None to its first ``after`` questions (the request came while the move ran)."""

    def __init__(self, flag, after):
        self.flag, self.after = flag, after

    def stop_requested(self, wait_s=0.0):
        self.after -= 1
        return None if self.after >= 0 else self.flag.stop_requested(wait_s)


def test_without_a_stop_flag_the_capture_completes_and_waits_its_settle(tmp_path):
    plan = Plan(2, (0.0,), settle_s=0.2)
    started = time.monotonic()
    capture(StandInOrbit(), Camera(), Phantom(), plan, _folder(tmp_path, plan))
    assert time.monotonic() - started >= 0.4 and _record(tmp_path)["status"] == "complete"


def test_each_frame_is_recorded_at_the_angle_the_rig_reported_not_the_planned_one(tmp_path):
    plan = Plan(4, (0.0, 30.0), settle_s=0.0)
    orbit, flag = StandInOrbit(), Flag()
    capture(orbit, Camera(), Phantom(), plan, _folder(tmp_path, plan), stop=flag)
    record = _record(tmp_path)
    assert record["status"] == "complete" and orbit.reads == 2 * 8  # before and after each picture
    recorded = [(frame["orbit_deg"], frame["elevation_deg"]) for frame in record["frames"]]
    assert recorded == [(orbit_deg + 0.0125, elevation_deg) for orbit_deg, elevation_deg in plan.stops()]


def test_a_frame_the_rig_was_moved_away_from_is_refused_not_recorded_at_the_planned_angle(tmp_path):
    """The red team's case: another client turned the orbit 34.6 deg during a settle; frame 0 was recorded at
    -180.00 deg and the capture ended complete."""
    plan = Plan(4, (0.0,), settle_s=0.0)
    orbit = StandInOrbit(offset_deg=34.6, moved_at=0)
    with pytest.raises(CaptureError, match=r"aborted after 0 of 4 pictures: picture 0: the rig reported the orbit at "
                                           r"-145\.39 deg .*planned -180\.00 deg .*moved during the scan"):
        capture(orbit, Camera(), Phantom(), plan, _folder(tmp_path, plan), stop=Flag())
    record = _record(tmp_path)
    assert record["status"] == "aborted" and record["frames"] == [] and orbit.released == 1


@pytest.mark.parametrize("offset_deg, kept", [(MAX_ANGLE_ERROR_DEG * 0.5, True), (MAX_ANGLE_ERROR_DEG * 1.5, False)])
def test_the_angle_bound(tmp_path, offset_deg, kept):
    plan = Plan(1, (0.0,), settle_s=0.0)
    orbit = StandInOrbit(offset_deg=offset_deg - 0.0125, moved_at=0)
    if kept:
        capture(orbit, Camera(), Phantom(), plan, _folder(tmp_path, plan))
        assert _record(tmp_path)["frames"][0]["orbit_deg"] == pytest.approx(-180.0 + offset_deg)
    else:
        with pytest.raises(CaptureError, match="more than 0.1 deg off"):
            capture(orbit, Camera(), Phantom(), plan, _folder(tmp_path, plan))


def test_a_virtual_placement_of_the_target_there_is_not_is_refused():
    from phantom.scan.virtual import VIRTUAL_PLACEMENTS, target_pose_facing, virtual_placement

    with pytest.raises(PhantomError, match=r"--placement is 0\.\.1 on the virtual rig, got 2"):
        virtual_placement(2)
    from phantom.scan.render import CharucoTarget

    facing = target_pose_facing(*VIRTUAL_PLACEMENTS[1], CharucoTarget())
    assert np.array_equal(virtual_placement(1).rotation, facing.rotation)


def test_a_scenes_targets_are_its_steps_volumes_once_each_in_order(tmp_path):
    from phantom.scan.validation import scene_targets_ml

    scene = tmp_path / "scene.toml"
    scene.write_text("[[steps]]\nvolume_ml = 30\n[[steps]]\nvolume_ml = 27.5\n[[steps]]\nvolume_ml = 30\n"
                     "[[steps]]\npressures_kpa = [1, 1, 1]\n")
    assert scene_targets_ml(str(scene)) == [30.0, 27.5]
    scene.write_text("[[steps]]\npressures_kpa = [1, 1, 1]\n")
    with pytest.raises(PhantomError, match="has no \\[\\[steps\\]\\] with volume_ml: give --targets"):
        scene_targets_ml(str(scene))


class RenderingCamera(Camera):
    """A camera that renders (as the virtual one): each picture taken at its moment and developed later, in
    whichever thread; a develop fails at picture ``fail_at``."""

    def __init__(self, orbit, fail_at=None):
        self.orbit, self.fail_at, self.log, self.taken = orbit, fail_at, [], 0

    def take(self):
        number, self.taken = self.taken, self.taken + 1
        self.log.append(("take", number, len(self.orbit.moves)))

        def develop():
            time.sleep(0.02)  # a render's time: the next move is asked meanwhile
            self.log.append(("develop", number, len(self.orbit.moves), threading.current_thread().name))
            if number == self.fail_at:
                raise PhantomError("the render failed")
            return np.full((8, 8, 3), number, np.uint8)
        return develop


def test_a_rendered_picture_is_developed_and_written_while_the_rig_moves_to_the_next_stop(tmp_path):
    """The daemon's scan (no progress callback): picture k is rendered and written in the capture's own thread
    while move k+1 runs, in the order taken, each written picture the one taken at its stop; the folder ends
    complete with every frame's stage times."""
    plan = Plan(5, (0.0,), settle_s=0.0)
    orbit = StandInOrbit()
    camera = RenderingCamera(orbit)
    folder = capture(orbit, camera, Phantom(), plan, _folder(tmp_path, plan), stop=Flag())
    assert folder.status == "complete" and len(folder.frames) == 5
    developed = [entry for entry in camera.log if entry[0] == "develop"]
    assert [entry[1] for entry in developed] == [0, 1, 2, 3, 4]
    assert all(name.startswith("capture-pictures") for *_, name in developed)
    # the picture of stop k (k+1 moves made when taken) developed after move k+2 was asked, the last one excepted
    assert sum(moves > number + 1 for _, number, moves, _ in developed) >= 3, camera.log
    for frame in CaptureFolder.open(tmp_path / "capture").frames:
        assert int(folder.image(frame)[0, 0, 0]) == frame.index and set(frame.stage_s) >= {"move", "grab", "write"}


def test_a_render_that_fails_aborts_the_capture_with_the_pictures_before_it_kept(tmp_path):
    plan = Plan(6, (0.0,), settle_s=0.0)
    orbit = StandInOrbit()
    with pytest.raises(CaptureError, match="capture aborted after 2 of 6 pictures: the render failed; the motors "
                                           "are released"):
        capture(orbit, RenderingCamera(orbit, fail_at=2), Phantom(), plan, _folder(tmp_path, plan), stop=Flag())
    data = json.loads((tmp_path / "capture" / "capture.json").read_text())
    assert data["status"] == "aborted" and len(data["frames"]) == 2 and orbit.released == 1
    assert len(orbit.moves) <= 4  # the failure is seen when the next picture is handed over: one move later
