"""The Rerun recording: a real .rrd written by Recorder and read back with rerun's RrdReader.

What a person sees depends on what is in the file: the entities (chambers named as people name them), the
``scene_time`` timeline, one colour per chamber, a drawing order in which nothing hides, the mesh's normals, the
translucent rest-shape ghost, the anatomical axes and the blueprint. The files: complete (a footer, which
``rerun rrd verify`` checks), never overwritten, one daemon per path, segments for long sessions, a pause on a
full disk and a resume; a file cut short in the middle of a message (a disk that filled up under the writer) is
read up to that message, saying so. Errors: a recording that cannot be written is a one-line PhantomError from
``open()``, and nothing is touched before ``open()``.
"""

from __future__ import annotations

import re
import struct
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from phantom import PhantomError
from phantom.host import recording as recording_module
from phantom.host.recording import (
    CHAMBER_COLOURS,
    GLAND_SERIES,
    PAUSE_BELOW_BYTES,
    RESUME_ABOVE_BYTES,
    Recorder,
    RecordingCutShort,
    RecordingError,
    entity_part,
    read_points_at,
    read_rrd,
    vertex_normals,
)

RERUN = Path(sys.executable).with_name("rerun")

NAMES = ["base", "left lobe", "right lobe"]


def uv_sphere(radius: float, rings: int = 24, segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A closed UV sphere (poles + rings x segments), triangles counter-clockwise seen from outside."""
    polar = np.linspace(0, np.pi, rings + 1)[1:-1]
    azimuth = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    p, a = np.meshgrid(polar, azimuth, indexing="ij")
    ring_points = np.stack([np.sin(p) * np.cos(a), np.sin(p) * np.sin(a), np.cos(p)], axis=-1).reshape(-1, 3)
    points = np.vstack([[0, 0, 1], ring_points, [0, 0, -1]]) * radius
    north, south = 0, len(points) - 1

    def vertex(ring, segment):
        return 1 + ring * segments + segment % segments

    triangles = [(north, vertex(0, s), vertex(0, s + 1)) for s in range(segments)]
    for ring in range(rings - 2):
        for s in range(segments):
            triangles += [(vertex(ring, s), vertex(ring + 1, s), vertex(ring + 1, s + 1)),
                          (vertex(ring, s), vertex(ring + 1, s + 1), vertex(ring, s + 1))]
    triangles += [(vertex(rings - 2, s), south, vertex(rings - 2, s + 1)) for s in range(segments)]
    return points, np.asarray(triangles)


def packed_rgba(rgb, alpha=255) -> int:
    """Rerun stores a colour as one u32, 0xRRGGBBAA."""
    r, g, b = rgb
    return (r << 24) | (g << 16) | (b << 8) | alpha


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "sub" / "run.rrd"  # a missing folder is created
    rest, triangles = uv_sphere(20.0)
    recorder = Recorder(NAMES, save_path=path)
    assert not path.exists(), "Recorder() must open nothing"
    recorder.open()
    recorder.log_rest_surface(rest, triangles)
    for k in range(40):
        time_s = 0.1 * k
        scene_s = time_s - 2.0 if time_s >= 2.0 else None  # a scene starts at 2 s
        recorder.set_scene_time(scene_s)
        recorder.log_telemetry(time_s, [0.01 * k, 0.02 * k, 0.03 * k], [1.0, 2.0, 3.0], [0.5, 0.25, 0.125])
        if k % 5 == 0:
            recorder.log_volumes(time_s, 30.0, 26.0 + 0.1 * k, [2.0, 1.1, 1.2], true_ml=27.0 + 0.1 * k)
    recorder.log_mesh(3.8, rest * 1.05, triangles)
    recorder.log_scanned_volume(3.85, 31.0, 2, 0.3)
    recorder.log_scan_surface(3.85, rest * 1.07, triangles)
    recorder.log_mesh(3.9, rest * 1.1, triangles)
    recorder.set_scene_time(None)
    recorder.log_event(4.0, "daemon stopped")
    recorder.close()
    return {"path": path, "entities": read_rrd(path), "rest": rest, "triangles": triangles}


def scalars(column):
    return [values[0] for values in column]


def test_the_entities_are_in_the_file_under_path_safe_chamber_names(recording):
    entities = recording["entities"]
    assert entity_part("left lobe") == "left_lobe"
    for part in ("base", "left_lobe", "right_lobe"):
        for series in ("measured_kpa", "commanded_kpa", "drive_level"):
            assert len(entities[f"/chamber/{part}/{series}"]["Scalars:scalars"]) == 40
        assert scalars(entities[f"/volume/chambers/{part}_ml"]["Scalars:scalars"]) == pytest.approx(
            [{"base": 2.0, "left_lobe": 1.1, "right_lobe": 1.2}[part]] * 8)
    assert scalars(entities["/chamber/right_lobe/measured_kpa"]["Scalars:scalars"]) == pytest.approx(
        [0.03 * k for k in range(40)])
    assert scalars(entities["/volume/true_ml"]["Scalars:scalars"]) == pytest.approx([27.0 + 0.5 * k for k in range(8)])
    assert scalars(entities["/volume/commanded_ml"]["Scalars:scalars"]) == [30.0] * 8
    assert scalars(entities["/events"]["TextLog:text"]) == ["daemon stopped"]


def test_scene_time_stamps_what_is_logged_while_a_scene_runs(recording):
    columns = recording["entities"]["/chamber/base/measured_kpa"]
    times, scene_times = columns["time"], columns["scene_time"]
    assert times == pytest.approx([0.1 * k for k in range(40)])
    for time_s, scene_s in zip(times, scene_times, strict=True):
        if time_s < 2.0 - 1e-9:
            assert scene_s is None
        else:
            assert scene_s == pytest.approx(time_s - 2.0, abs=1e-6)
    # after set_scene_time(None) nothing is stamped
    assert recording["entities"]["/events"]["scene_time"] == [None]


def test_each_chamber_has_its_own_colour_and_name_in_every_plot(recording):
    entities = recording["entities"]
    seen = set()
    for index, (name, part) in enumerate(zip(NAMES, ("base", "left_lobe", "right_lobe"), strict=True)):
        colour = packed_rgba(CHAMBER_COLOURS[index])
        for series, legend in (("measured_kpa", f"{name} measured"), ("drive_level", name)):
            style = entities[f"/chamber/{part}/{series}"]
            assert style["SeriesLines:colors"] == [[colour]]
            assert style["SeriesLines:names"] == [[legend]]
        assert entities[f"/volume/chambers/{part}_ml"]["SeriesLines:colors"] == [[colour]]
        setpoint = entities[f"/chamber/{part}/commanded_kpa"]
        assert setpoint["SeriesLines:names"] == [[f"{name} setpoint"]]
        (setpoint_colour,), = setpoint["SeriesLines:colors"]
        assert setpoint_colour >> 8 == colour >> 8 and setpoint_colour & 0xFF < 255  # same hue, translucent
        assert setpoint["SeriesLines:widths"][0][0] > style["SeriesLines:widths"][0][0]  # wider than measured
        seen.add(colour)
    assert len(seen) == 3


def test_the_mesh_has_outward_unit_normals(recording):
    mesh = recording["entities"]["/phantom/mesh"]
    positions = np.asarray(mesh["Mesh3D:vertex_positions"][-1])
    normals = np.asarray(mesh["Mesh3D:vertex_normals"][-1])
    assert positions.shape == normals.shape == (len(recording["rest"]), 3)
    # on a sphere about the origin the outward normal is the position's direction; the angle between them on a
    # 24 x 48 UV sphere is at most a few degrees (0.995 = 5.7 degrees)
    radial = positions / np.linalg.norm(positions, axis=1, keepdims=True)
    assert np.linalg.norm(normals, axis=1) == pytest.approx(1.0, abs=1e-5)
    assert np.min(np.sum(normals * radial, axis=1)) > 0.995


def test_a_moving_surface_logs_its_triangles_once(recording):
    mesh = recording["entities"]["/phantom/mesh"]
    assert len(mesh["time"]) == 2
    triangles = mesh["Mesh3D:triangle_indices"]
    assert np.array_equal(triangles[0], recording["triangles"]) and triangles[1] is None
    assert np.allclose(mesh["Mesh3D:vertex_positions"][0], recording["rest"] * 1.05, atol=1e-4)


def test_a_scans_surface_stands_over_the_models_in_the_scanned_volumes_green(recording):
    scan = recording["entities"]["/phantom/scan"]
    assert scan["time"] == pytest.approx([3.85])
    assert np.allclose(scan["Mesh3D:vertex_positions"][0], recording["rest"] * 1.07, atol=1e-4)
    assert np.array_equal(scan["Mesh3D:triangle_indices"][0], recording["triangles"])
    (albedo,), = scan["Mesh3D:albedo_factor"]
    assert albedo >> 8 == packed_rgba(GLAND_SERIES["scanned_ml"][1][:3]) >> 8 and 0 < albedo & 0xFF < 255
    assert scalars(recording["entities"]["/volume/scanned_ml"]["Scalars:scalars"]) == [31.0]
    assert scalars(recording["entities"]["/verify/round"]["Scalars:scalars"]) == [2.0]
    assert scalars(recording["entities"]["/verify/tolerance_pct"]["Scalars:scalars"]) == [0.3]
    assert recording["entities"]["/verify/round"]["time"] == pytest.approx([3.85])


def test_vertex_normals_flip_with_the_winding():
    points, triangles = uv_sphere(1.0, rings=8, segments=12)
    outward = vertex_normals(points, triangles)
    inward = vertex_normals(points, triangles[:, ::-1])
    assert np.allclose(outward, -inward)


def test_the_rest_shape_is_a_static_translucent_ghost(recording):
    rest = recording["entities"]["/phantom/rest"]
    assert "time" not in rest  # static: shown at every time
    assert np.allclose(rest["Mesh3D:vertex_positions"][0], recording["rest"], atol=1e-5)
    assert len(rest["Mesh3D:vertex_normals"][0]) == len(recording["rest"])
    (albedo,), = rest["Mesh3D:albedo_factor"]
    assert 0 < albedo & 0xFF < 128
    deformed_albedo = recording["entities"]["/phantom/mesh"]["Mesh3D:albedo_factor"][0][0]
    assert deformed_albedo & 0xFF > albedo & 0xFF  # the deformed surface is the more opaque
    assert "ViewCoordinates:xyz" in recording["entities"]["/phantom"]


def test_the_blueprint_is_in_the_file(recording):
    from rerun.chunk import RrdReader

    reader = RrdReader(str(recording["path"]))
    blueprints = reader.blueprints()
    # the layout at open(), and the one with the phantom view once the rest shape was known
    assert len(blueprints) == 2
    assert all(entry.application_id == "phantom" for entry in blueprints)
    view_names = []
    for entry in blueprints:
        names = set()
        for chunk in reader.stream(store=entry).collect().stream():
            batch = chunk.to_record_batch()
            for column in batch.column_names:
                if column.endswith(":display_name"):
                    names.update(value for values in batch.column(column).to_pylist() for value in values or [])
        view_names.append(names)
    plots = {f"{name}: {quantity}" for name in NAMES for quantity in ("pressure (kPa)", "drive (0-1)", "volume (ml)")}
    plots |= {"gland volume (ml)", "link", "solver (ms)", "correction (ml; measurements)", "events"}
    phantom = "phantom (mm, grid 10 mm): deformed over the rest shape"
    assert sorted(view_names, key=len) == [plots, plots | {phantom}]


def test_nothing_is_recorded_or_opened_without_a_destination(tmp_path):
    recorder = Recorder(NAMES)
    recorder.open()
    assert not recorder.enabled and not recorder.wants_mesh
    recorder.log_telemetry(0.0, [1, 2, 3], [1, 2, 3], [0, 0, 0])
    recorder.close()


def test_recorder_touches_no_file_before_open(tmp_path):
    path = tmp_path / "another_daemons.rrd"
    path.write_bytes(b"precious")
    Recorder(NAMES, save_path=path)
    assert path.read_bytes() == b"precious"


@pytest.mark.parametrize("where, reason", [
    ("file/run.rrd", "a part of the path is not a directory"),
    ("folder", "it is a directory"),
    ("/dev/full", "the disk is full"),
])
def test_open_on_an_unwritable_path_is_one_line(tmp_path, where, reason):
    (tmp_path / "file").write_text("a regular file where a folder should be")
    (tmp_path / "folder").mkdir()
    path = where if where.startswith("/") else tmp_path / where
    recorder = Recorder(NAMES, save_path=path)
    with pytest.raises(PhantomError) as caught:
        recorder.open()
    message = str(caught.value)
    assert "\n" not in message and reason in message and str(path) in message
    assert not recorder.enabled


def test_chamber_names_that_collide_in_paths_are_refused():
    with pytest.raises(PhantomError, match="collide"):
        Recorder(["left lobe", "left_lobe"], save_path="unused.rrd")


def test_the_target_is_drawn_as_dots_so_that_no_line_bridges_a_time_without_one(recording, tmp_path):
    style = recording["entities"]["/volume/commanded_ml"]
    assert "SeriesPoints:colors" in style and "SeriesLines:colors" not in style
    path = tmp_path / "targets.rrd"
    recorder = Recorder(NAMES, save_path=path)
    recorder.open()
    for time_s, target_ml in enumerate([30.0, 31.0, None, None, 32.0]):
        recorder.log_volumes(time_s, target_ml, 26.0)
    recorder.close()
    target = read_rrd(path)["/volume/commanded_ml"]
    assert target["time"] == [0.0, 1.0, 4.0] and scalars(target["Scalars:scalars"]) == [30.0, 31.0, 32.0]


@pytest.mark.slow
def test_a_viewer_that_never_answers_neither_fails_open_nor_close():
    recorder = Recorder(NAMES, connect_url="rerun+http://127.0.0.1:1/proxy")  # nothing listens on port 1
    recorder.open()
    recorder.log_telemetry(0.0, [1, 2, 3], [1, 2, 3], [0, 0, 0])
    recorder.close()
    assert not recorder.enabled


def test_a_bad_viewer_address_is_one_line():
    with pytest.raises(PhantomError) as caught:
        Recorder(NAMES, connect_url="not a url").open()
    assert "\n" not in str(caught.value) and "not a url" in str(caught.value)


def test_what_was_asked_for_is_drawn_under_what_was_measured(recording):
    """Rerun draws a plot's series in the order of their entity paths, the last on top (whatever order the
    blueprint lists them in): the setpoint and the target must sort before the measured pressure and the
    estimate, and be the wider, translucent ones, so that both show where they coincide."""
    entities = recording["entities"]
    for part in ("base", "left_lobe", "right_lobe"):
        setpoint, measured = f"/chamber/{part}/commanded_kpa", f"/chamber/{part}/measured_kpa"
        assert sorted([measured, setpoint]) == [setpoint, measured]
        assert entities[setpoint]["SeriesLines:widths"][0][0] > 2 * entities[measured]["SeriesLines:widths"][0][0]
    gland = [f"/volume/{series}" for series in GLAND_SERIES]
    assert sorted(gland) == gland and gland[0] == "/volume/commanded_ml"
    target_size = entities["/volume/commanded_ml"]["SeriesPoints:marker_sizes"][0][0]
    assert target_size > 2 * entities["/volume/estimated_ml"]["SeriesLines:widths"][0][0]
    (target_colour,), = entities["/volume/commanded_ml"]["SeriesPoints:colors"]
    assert target_colour & 0xFF < 255


def test_the_phantom_view_has_labelled_anatomical_axes_at_a_stated_scale(recording):
    axes = recording["entities"]["/phantom/axes"]
    vectors = np.asarray(axes["Arrows3D:vectors"][0])
    assert np.allclose(vectors, 10.0 * np.eye(3))
    labels = axes["Arrows3D:labels"][0]
    assert [label.split(":")[0] for label in labels] == ["x", "y", "z"]
    assert all("10 mm" in label for label in labels) and "anterior" in labels[1] and "base" in labels[2]
    # beside the rest shape, not inside it, and in front of it (+y, where the camera is), not hidden behind it
    origin = np.asarray(axes["Arrows3D:origins"][0][0])
    low, high = recording["rest"].min(axis=0), recording["rest"].max(axis=0)
    assert origin[0] < low[0] and origin[1] > high[1] and origin[2] < low[2]


def test_rerun_verifies_the_file(recording):
    result = subprocess.run([str(RERUN), "rrd", "verify", str(recording["path"])], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def record_a_little(path: Path, value: float, **options) -> Recorder:
    recorder = Recorder(NAMES, save_path=path, **options)
    recorder.open()
    recorder.log_volumes(0.0, value, value)
    return recorder


def test_an_existing_recording_is_set_aside_never_overwritten(tmp_path):
    path = tmp_path / "run.rrd"
    record_a_little(path, 30.0).close()
    first = path.read_bytes()
    crashed = tmp_path / "crashed.rrd"
    crashed.write_bytes(b"a crashed session's recording, without its footer")
    recorder = record_a_little(path, 31.0)
    recorder.close()
    (aside,) = recorder.set_aside
    assert aside.parent == tmp_path and aside.name.startswith("run.") and aside.suffix == ".rrd"
    assert aside.read_bytes() == first
    assert scalars(read_rrd(path)["/volume/estimated_ml"]["Scalars:scalars"]) == [31.0]
    # a second set-aside in the same second gets its own name
    again = record_a_little(path, 32.0)
    again.close()
    assert len({aside, *again.set_aside}) == 2 and all(p.exists() for p in (aside, *again.set_aside))
    assert crashed.read_bytes().startswith(b"a crashed")


def test_a_path_another_daemon_records_to_is_refused_and_left_alone(tmp_path):
    path = tmp_path / "run.rrd"
    live = record_a_little(path, 30.0)
    try:
        with pytest.raises(RecordingError) as caught:
            Recorder(NAMES, save_path=path).open()
        message = str(caught.value)
        assert "\n" not in message and "another daemon" in message and str(path) in message
        assert not list(tmp_path.glob("run.*.rrd")), "the live recording must not be set aside"
    finally:
        live.close()
    assert scalars(read_rrd(path)["/volume/estimated_ml"]["Scalars:scalars"]) == [30.0]
    record_a_little(path, 31.0).close()  # free again once its daemon has closed it


def test_a_second_process_is_refused_while_the_first_holds_the_path(tmp_path):
    """The lock is the kernel's (flock), so another process sees it, and it goes with the process that held it."""
    path = tmp_path / "run.rrd"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\n"
        "from phantom.host.recording import Recorder\n"
        f"r = Recorder(['a', 'b', 'c'], save_path={str(path)!r}); r.open(); print('open', flush=True)\n"
        "sys.stdin.readline()\n")], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "open"
        with pytest.raises(RecordingError, match=f"process {holder.pid}"):
            Recorder(NAMES, save_path=path).open()
    finally:
        holder.kill()  # dies without closing: the kernel releases its lock
        holder.wait(10)
    recorder = record_a_little(path, 30.0)
    recorder.close()
    assert len(recorder.set_aside) == 1  # the dead holder's file was kept


class FakeDisk:
    """A clock and a free-space reading that the test moves."""

    def __init__(self):
        self.now_s = 0.0
        self.free = 10 * RESUME_ABOVE_BYTES

    def clock(self) -> float:
        return self.now_s

    def free_space(self, folder: Path) -> int:
        return self.free


def measured_base_kpa_in(path: Path) -> list[float]:
    """The base chamber's measured pressures in a file still being written (read up to its last message)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingCutShort)  # no footer yet
        return scalars(read_rrd(path).get("/chamber/base/measured_kpa", {}).get("Scalars:scalars", []))


def test_telemetry_is_sent_in_batches_and_the_control_loops_check_sends_what_waits(tmp_path):
    """Telemetry frames are held for TELEMETRY_BATCH_S and sent a column a series (a value logged at a time cost the
    daemon's loop 2.8 % of a core); the control loop's check() sends frames held that long, so a board that goes
    quiet leaves nothing unsent; a value that is not finite is left out of its series alone."""
    disk = FakeDisk()
    path = tmp_path / "run.rrd"
    recorder = Recorder(NAMES, save_path=path, clock=disk.clock, free_space=disk.free_space)
    recorder.open()
    batch_s = recording_module.TELEMETRY_BATCH_S
    for k in range(5):
        disk.now_s = 0.02 * k
        recorder.log_telemetry(disk.now_s, [0.1 * k, 0.2, 0.3], [np.nan if k == 2 else 1.0, 2.0, 3.0], [0.5] * 3)
    recorder.check()
    recorder._stream.flush(timeout_sec=10.0)
    assert measured_base_kpa_in(path) == [], "sent before its batch was full"
    disk.now_s = batch_s  # the board went quiet: the next check sends what waits
    recorder.check()
    recorder._stream.flush(timeout_sec=10.0)
    assert measured_base_kpa_in(path) == pytest.approx([0.1 * k for k in range(5)])
    disk.now_s = 2 * batch_s  # frames keep coming: the frame a batch's time after the first sends them all
    recorder.log_telemetry(disk.now_s, [1.0, 0.2, 0.3], [1.0, 2.0, 3.0], [0.5] * 3)
    disk.now_s = 3 * batch_s
    recorder.log_telemetry(disk.now_s, [2.0, 0.2, 0.3], [1.0, 2.0, 3.0], [0.5] * 3)
    recorder._stream.flush(timeout_sec=10.0)
    assert measured_base_kpa_in(path)[5:] == pytest.approx([1.0, 2.0])
    recorder.log_telemetry(disk.now_s + 0.02, [3.0, 0.2, 0.3], [1.0, 2.0, 3.0], [0.5] * 3)
    recorder.close()  # what is held is written with the file's end
    entities = read_rrd(path)
    assert scalars(entities["/chamber/base/measured_kpa"]["Scalars:scalars"]) == pytest.approx(
        [0.0, 0.1, 0.2, 0.3, 0.4, 1.0, 2.0, 3.0])
    assert entities["/chamber/base/commanded_kpa"]["time"] == pytest.approx([0.0, 0.02, 0.06, 0.08, 1.0, 1.5, 1.52])
    assert len(entities["/chamber/left_lobe/commanded_kpa"]["time"]) == 8


def test_a_full_disk_pauses_the_recording_with_an_event_and_it_resumes_in_a_new_file(tmp_path):
    disk, told = FakeDisk(), []
    path = tmp_path / "run.rrd"
    recorder = Recorder(NAMES, save_path=path, clock=disk.clock, free_space=disk.free_space,
                        on_problem=lambda text, level: told.append((level, text)))
    recorder.open()
    recorder.log_volumes(0.0, 30.0, 30.0)
    disk.now_s, disk.free = 10.0, PAUSE_BELOW_BYTES // 2
    recorder.check()
    assert recorder.state == "paused" and not recorder.enabled
    assert told[-1][0] == "ERROR" and "paused" in told[-1][1] and "MB" in told[-1][1]
    assert recorder.status()["problem"]
    recorder.log_volumes(1.0, 31.0, 31.0)  # dropped while paused
    disk.now_s, disk.free = 20.0, RESUME_ABOVE_BYTES - 1
    recorder.check()
    assert recorder.state == "paused"  # not enough yet
    disk.now_s, disk.free = 30.0, RESUME_ABOVE_BYTES
    recorder.check()
    assert recorder.state == "recording" and told[-1] == ("INFO", told[-1][1]) and "resumed" in told[-1][1]
    recorder.log_volumes(2.0, 32.0, 32.0)
    recorder.close()
    first, second = recorder.files
    assert first != path and second == path
    assert scalars(read_rrd(first)["/volume/estimated_ml"]["Scalars:scalars"]) == [30.0]
    assert scalars(read_rrd(second)["/volume/estimated_ml"]["Scalars:scalars"]) == [32.0]
    for part in (first, second):
        assert subprocess.run([str(RERUN), "rrd", "verify", str(part)], capture_output=True).returncode == 0


def test_a_file_that_stops_growing_while_data_comes_is_reported(tmp_path, monkeypatch):
    disk, told = FakeDisk(), []
    recorder = Recorder(NAMES, save_path=tmp_path / "run.rrd", clock=disk.clock, free_space=disk.free_space,
                        on_problem=lambda text, level: told.append(text))
    recorder.open()
    recorder.check()
    monkeypatch.setattr(recording_module, "file_size", lambda path: 1234)  # the writer has stopped
    for k in range(1, 10):
        disk.now_s = 2.5 * k
        recorder.log_volumes(disk.now_s, 30.0, 30.0)
        recorder.check()
    assert recorder.state == "paused" and "stopped growing" in told[-1] and len(told) == 1
    monkeypatch.undo()
    disk.now_s += recording_module.RETRY_AFTER_S
    recorder.check()
    assert recorder.state == "recording" and "resumed" in told[-1] and len(recorder.files) == 2
    recorder.close()


def test_a_file_whose_writer_is_only_late_is_not_called_stalled(tmp_path, monkeypatch):
    """On a busy machine the SDK's writer may not have written for a while: asked to write out what is queued,
    it does, and the recording goes on."""
    disk, told = FakeDisk(), []
    recorder = Recorder(NAMES, save_path=tmp_path / "run.rrd", clock=disk.clock, free_space=disk.free_space,
                        on_problem=lambda text, level: told.append(text))
    recorder.open()
    recorder.check()
    flushed = []
    monkeypatch.setattr(recording_module, "file_size", lambda path: 1234 + 100 * len(flushed))
    stream_flush = recorder._stream.flush
    monkeypatch.setattr(recorder._stream, "flush", lambda **kwargs: (flushed.append(1), stream_flush(**kwargs)))
    for k in range(1, 10):
        disk.now_s = 2.5 * k
        recorder.log_volumes(disk.now_s, 30.0, 30.0)
        recorder.check()
    assert flushed and recorder.state == "recording" and not told
    recorder.close()


def test_a_long_session_is_written_in_segments_each_complete(tmp_path, monkeypatch):
    disk = FakeDisk()
    monkeypatch.setattr(recording_module, "SEGMENT_S", 60.0)
    path = tmp_path / "run.rrd"
    recorder = Recorder(NAMES, save_path=path, clock=disk.clock, free_space=disk.free_space)
    recorder.open()
    rest, triangles = uv_sphere(10.0, rings=6, segments=8)
    recorder.log_rest_surface(rest, triangles)
    for minute in range(3):
        disk.now_s = 60.0 * minute + 1.0
        recorder.check()
        recorder.log_volumes(disk.now_s, 30.0 + minute, 30.0 + minute)
        recorder.log_mesh(disk.now_s, rest * 1.01, triangles)
    recorder.close()
    assert len(recorder.files) == 3 and recorder.files[-1] == path and not recorder.set_aside
    for minute, part in enumerate(recorder.files):
        entities = read_rrd(part)
        assert scalars(entities["/volume/estimated_ml"]["Scalars:scalars"]) == [30.0 + minute]
        # each segment stands alone: styles, the rest shape, the axes, the whole mesh
        assert "/phantom/rest" in entities and "/phantom/axes" in entities
        assert entities["/phantom/mesh"]["Mesh3D:triangle_indices"][0] is not None
        assert subprocess.run([str(RERUN), "rrd", "verify", str(part)], capture_output=True).returncode == 0


def test_a_real_full_disk_pauses_the_recording(tmp_path):
    """On a 2 MB tmpfs (where this machine lets the tests mount one): the recording pauses before the SDK's
    writer fails, and the file it closed is complete."""
    small = tmp_path / "small"
    small.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(small)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        told = []
        recorder = Recorder(NAMES, save_path=small / "run.rrd", on_problem=lambda text, level: told.append(text))
        recorder.open()  # 64 KiB written and truncated: there is room
        recorder.check()
        assert recorder.state == "paused" and "MB are free" in told[-1]
        recorder.close()
        assert subprocess.run([str(RERUN), "rrd", "verify", str(small / "run.rrd")],
                              capture_output=True).returncode == 0
    finally:
        subprocess.run(["umount", str(small)], check=True)


def message_starts(data: bytes) -> list[int]:
    """Where each message of an .rrd stream begins: after the stream's 12-byte header ("RRF2", its version and
    options), each message is a 16-byte header (its kind and its payload's length, little-endian u64s) and the
    payload; kind 0 ends the stream (its payload the footer)."""
    starts, at = [], 12
    while at + 16 <= len(data):
        starts.append(at)
        kind, length = struct.unpack_from("<QQ", data, at)
        at += 16 + length
        if kind == 0:
            break
    return starts


@pytest.fixture(scope="module")
def unfinished(tmp_path_factory):
    """A recording as a writer that stopped leaves it: whole messages and no footer."""
    path = tmp_path_factory.mktemp("unfinished") / "run.rrd"
    rest, triangles = uv_sphere(10.0, rings=6, segments=8)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(recording_module, "WRITE_FOOTER", False)
        recorder = Recorder(NAMES, save_path=path)
        recorder.open()
        recorder.log_rest_surface(rest, triangles)
        for k in range(20):
            recorder.log_telemetry(0.1 * k, [0.01 * k] * 3, [1.0, 2.0, 3.0], [0.5, 0.25, 0.125])
            recorder.log_volumes(0.1 * k, 30.0, 26.0 + 0.1 * k, [2.0, 1.1, 1.2])
            recorder.log_mesh(0.1 * k, rest * (1 + 0.01 * k), triangles)
        recorder.log_event(2.0, "daemon stopped")
        recorder.close()
    return path


@pytest.mark.parametrize("where", ["payload", "header", "footer"])
def test_a_recording_cut_short_in_its_last_message_is_read_up_to_it_and_says_so(recording, unfinished, where,
                                                                                 tmp_path):
    """A disk that filled up stopped the SDK's writer in the middle of a message (its payload, its header, or the
    footer of a file being closed): rerun's reader refused the whole file ("Message payload ... exceeds file
    size"). Everything before that message is read, as a file that ends where a message does (a killed daemon's)
    is read, and read_rrd warns that the file ends cut short and how many bytes were not read."""
    data = (recording["path"] if where == "footer" else unfinished).read_bytes()
    last = message_starts(data)[-1]
    kind, length = struct.unpack_from("<QQ", data, last)
    assert (kind == 0) == (where == "footer") and length > 40
    cut = {"payload": last + 16 + length // 2, "header": last + 7, "footer": last + 16 + 10}[where]
    whole, cut_short = tmp_path / "whole.rrd", tmp_path / "cut.rrd"
    whole.write_bytes(data[:last])  # the messages before the one cut: rerun reads such a file as it is
    cut_short.write_bytes(data[:cut])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RecordingCutShort)  # a file that ends where a message does is not cut short
        expected = read_rrd(whole)
    with pytest.warns(RecordingCutShort, match=f"{cut_short} ends cut short.* its last {cut - last} bytes"):
        entities = read_rrd(cut_short)
    assert entities == expected
    assert {"/volume/estimated_ml", "/chamber/base/measured_kpa", "/phantom/rest"} <= set(entities)
    assert cut_short.read_bytes() == data[:cut], "the recording is left as it is"
    # the second pass (phantom report's surfaces) reads it too
    mesh_s = {time_s for time_s in entities.get("/phantom/mesh", {}).get("time", []) if time_s is not None}
    with pytest.warns(RecordingCutShort):
        found = read_points_at(cut_short, "/phantom/mesh", "Mesh3D:vertex_positions", mesh_s)
    assert set(found) == mesh_s


def readme_entities(parts: list[str]) -> set[str]:
    """The entity paths host/README.md's recording table lists (``a/b/c, d`` is ``a/b/c`` and ``a/b/d``), each
    ``<chamber>`` made each of ``parts``."""
    text = (Path(__file__).resolve().parents[1] / "host" / "README.md").read_text()
    table = text.split("`_`; the plots show the name itself):\n\n", 1)[1].split("\n\n", 1)[0]
    listed = set()
    for line in table.splitlines():
        if line.startswith("     ") and not line.startswith("    " + line.strip()):  # a note's next line
            continue
        names = re.split(r"\s{2,}", line.strip())[0]
        first, *others = names.split(", ")
        prefix = first.rsplit("/", 1)[0]
        paths = [first, *(other if "/" in other else f"{prefix}/{other}" for other in others)]
        listed |= {path.replace("<chamber>", part) for path in paths for part in parts}
    return {"/" + path for path in listed}


def test_the_readme_lists_every_entity_a_recording_holds(tmp_path):
    """host/README.md listed ``setpoint_kpa`` and ``volume/target_ml`` for entities the daemon writes as
    ``commanded_kpa`` and ``commanded_ml``, and left out the scan's, the correction's and the axes: code reading a
    recording by the README got a KeyError. Every ``log_`` method of the recorder is called here (a new one fails
    this test until it is), and what the file holds is what the README lists."""
    rest, triangles = uv_sphere(20.0)
    recorder = Recorder(NAMES, save_path=tmp_path / "all.rrd")
    recorder.open()
    calls = {
        "log_rest_surface": lambda: recorder.log_rest_surface(rest, triangles),
        "log_telemetry": lambda: recorder.log_telemetry(0.1, [0.1, 0.2, 0.3], [1.0, 2.0, 3.0], [0.5, 0.2, 0.1]),
        "log_volumes": lambda: recorder.log_volumes(0.1, 30.0, 29.0, [2.0, 1.1, 1.2], true_ml=29.5, model_ml=28.0),
        "log_correction": lambda: recorder.log_correction(0.2, 0.4, 3),
        "log_scanned_volume": lambda: recorder.log_scanned_volume(0.3, 29.9, 1, 0.3),
        "log_scan_surface": lambda: recorder.log_scan_surface(0.3, rest * 1.01, triangles),
        "log_link": lambda: recorder.log_link(0.4, 3.0, 0, 0, 0),
        "log_solver": lambda: recorder.log_solver(0.5, 0.001, 0.01),
        "log_event": lambda: recorder.log_event(0.6, "a target"),
        "log_mesh": lambda: recorder.log_mesh(0.7, rest * 1.02, triangles),
    }
    assert set(calls) == {name for name in dir(Recorder) if name.startswith("log_")}
    for call in calls.values():
        call()
    recorder.close()
    # not what a reader reads: a plot's style alone, the 3D view's axes' directions, Rerun's own properties
    held = {path for path, columns in read_rrd(tmp_path / "all.rrd").items()
            if any(column.split(":")[0] not in ("SeriesLines", "SeriesPoints", "ViewCoordinates", "time",
                                                "scene_time") for column in columns)} - {"/__properties"}
    assert held == readme_entities([entity_part(name) for name in NAMES])
