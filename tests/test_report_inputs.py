"""``phantom report`` reads what a recording says defensively (issue 51, item 4): triangle indices beyond the
vertices leave the pictures out and say why (was an IndexError traceback), a chamber named like mathtext is drawn
as its text (was matplotlib's ParseFatalException); a recording cut short in the middle of a message (a disk that
filled up under the writer) is reported up to that message, saying so (was refused as not a recording)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rerun")
pytest.importorskip("matplotlib")

from phantom.cli.report import load_run, write_report  # noqa: E402
from phantom.host.recording import Recorder  # noqa: E402


def _record(path, names, triangles_offset=0):
    rest = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], dtype=float)
    triangles = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]) + triangles_offset
    recorder = Recorder(names, save_path=path)
    recorder.open()
    recorder.log_rest_surface(rest, triangles)
    for k in range(10):
        recorder.log_telemetry(k / 10, [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5])
        recorder.log_volumes(k / 10, 30.0, 29.9, [2.0, 2.0, 2.0])
        recorder.log_mesh(k / 10, rest * (1 + k / 100), triangles)
    recorder.close()
    return path


def test_triangle_indices_beyond_the_vertices_leave_the_pictures_out_and_say_why(tmp_path, monkeypatch):
    import phantom.host.recording

    # a recording damaged or written by another program: the recorder's own normals would refuse these indices
    monkeypatch.setattr(phantom.host.recording, "vertex_normals", lambda positions, triangles: np.zeros_like(positions))
    path = _record(tmp_path / "run.rrd", ["base", "left lobe", "right lobe"], triangles_offset=100)
    run = load_run(path)
    assert run.surfaces is None
    assert any("triangle indices" in note and "103" in note for note in run.notes), run.notes
    text = write_report(path, tmp_path / "run.html").read_text()
    assert "triangle indices" in text and "The gland</h2>" not in text


def test_a_chamber_named_like_mathtext_is_drawn_as_its_text(tmp_path):
    names = [r"$\undefinedcommand$", "left $x^2$", "50% & <b>"]
    path = _record(tmp_path / "run.rrd", names)
    text = write_report(path, tmp_path / "run.html").read_text()
    assert "<b>" not in text.replace("<body>", "")
    assert [chamber.name for chamber in load_run(path).chambers] == names



def test_only_the_surfaces_pictured_are_read_and_they_are_the_recordings(tmp_path):
    """A 51 MB recording of 1500 surfaces of 2562 vertices: the report took 1.9 GB (every surface as lists of
    Python floats), 380 MB once only the pictured ones are read, in a second pass (177 MB for a 1.6 MB recording:
    the rest is the reader's copy of the recording), its HTML byte for byte the same (measured for the commit;
    here the mechanism: what is read, and that it is what was logged)."""
    from phantom.host.recording import read_rrd

    path = _record(tmp_path / "run.rrd", ["base", "left lobe", "right lobe"])
    run = load_run(path)
    assert run.surfaces is not None and len(run.surfaces.time_s) == 10
    # no steps: up to 12 frames spread over the recording are pictured, each the last logged before its time
    assert 0 < len(run.surfaces.positions_mm) <= 10
    mesh = read_rrd(path)["/phantom/mesh"]
    logged = dict(zip(mesh["time"], mesh["Mesh3D:vertex_positions"], strict=True))
    for time_s, kept in run.surfaces.positions_mm.items():
        assert kept.dtype == np.float32
        np.testing.assert_array_equal(kept, np.asarray(logged[time_s], dtype=np.float32))


def test_a_recording_cut_short_is_reported_up_to_the_cut_saying_so(tmp_path, monkeypatch, capsys):
    """The red team's full disk: the daemon's file ended in the middle of a message, without its footer, and
    ``phantom report`` said it "cannot be read as a Rerun recording". It reports what was written before, and
    says (on the page and on stderr) that the recording ends cut short."""
    import phantom.host.recording
    from phantom.cli.main import main

    monkeypatch.setattr(phantom.host.recording, "WRITE_FOOTER", False)  # as a writer that stopped leaves it
    path = _record(tmp_path / "run.rrd", ["base", "left lobe", "right lobe"])
    whole = path.read_bytes()
    path.write_bytes(whole[:-5])  # 5 bytes short of the end of its last message
    run = load_run(path)
    assert run.volumes and len(run.chambers) == 3
    (note,) = [note for note in run.notes if "cut short" in note]
    assert str(path) in note and "bytes" in note
    assert main(["report", str(path), "--out", str(tmp_path / "run.html")]) == 0
    assert "ends cut short" in capsys.readouterr().err
    text = (tmp_path / "run.html").read_text()
    assert "ends cut short" in text and "Chambers: pressure and drive" in text
