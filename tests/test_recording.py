"""The Rerun recording: a real .rrd written by Recorder and read back with rerun's RrdReader.

What a person sees depends on what is in the file: the entities, the ``scene_time`` timeline, one colour per
chamber, the mesh's normals, the translucent rest-shape ghost and the blueprint. Errors: a recording that cannot
be written is a one-line PhantomError from ``open()``, and nothing is touched before ``open()``.
"""

from __future__ import annotations

import numpy as np
import pytest

from phantom import PhantomError
from phantom.host.recording import CHAMBER_COLOURS, Recorder, entity_part, read_rrd, vertex_normals

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
        for series in ("measured_kpa", "setpoint_kpa", "drive_level"):
            assert len(entities[f"/chamber/{part}/{series}"]["Scalars:scalars"]) == 40
        assert scalars(entities[f"/volume/chambers/{part}_ml"]["Scalars:scalars"]) == pytest.approx(
            [{"base": 2.0, "left_lobe": 1.1, "right_lobe": 1.2}[part]] * 8)
    assert scalars(entities["/chamber/right_lobe/measured_kpa"]["Scalars:scalars"]) == pytest.approx(
        [0.03 * k for k in range(40)])
    assert scalars(entities["/volume/true_ml"]["Scalars:scalars"]) == pytest.approx([27.0 + 0.5 * k for k in range(8)])
    assert scalars(entities["/volume/target_ml"]["Scalars:scalars"]) == [30.0] * 8
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
        for series in ("measured_kpa", "drive_level"):
            style = entities[f"/chamber/{part}/{series}"]
            assert style["SeriesLines:colors"] == [[colour]]
            assert style["SeriesLines:names"] == [[name]]
        assert entities[f"/volume/chambers/{part}_ml"]["SeriesLines:colors"] == [[colour]]
        setpoint = entities[f"/chamber/{part}/setpoint_kpa"]
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

    # written without a footer, whose chunk index the SDK would keep in memory for the whole recording
    with pytest.warns(Warning, match="no footer"):
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
    plots = {"pressure (kPa): measured (thin), setpoint (wide)", "drive level (0-1)", "gland volume (ml)",
             "base (ml)", "left lobe (ml)", "right lobe (ml)", "link", "solver (ms)", "events"}
    phantom = "phantom (mm): deformed over the rest shape"
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
    style = recording["entities"]["/volume/target_ml"]
    assert "SeriesPoints:colors" in style and "SeriesLines:colors" not in style
    path = tmp_path / "targets.rrd"
    recorder = Recorder(NAMES, save_path=path)
    recorder.open()
    for time_s, target_ml in enumerate([30.0, 31.0, None, None, 32.0]):
        recorder.log_volumes(time_s, target_ml, 26.0)
    recorder.close()
    target = read_rrd(path)["/volume/target_ml"]
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
