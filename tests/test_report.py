"""``phantom report``: a recording written by the daemon's recorder, read back, as one self-contained HTML file;
rendered by headless Chromium (Debian's ``chromium``) to check that its plots and pictures show."""

from __future__ import annotations

import base64
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from phantom import PhantomError

pytest.importorskip("rerun")
pytest.importorskip("matplotlib")

from phantom.cli.report import Series, load_run, scans_in, scans_table, verified_targets, write_report  # noqa: E402
from phantom.host.recording import CHAMBER_COLOURS, Recorder  # noqa: E402

NAMES = ["base", "left lobe", "right lobe"]
#: The scene's steps: (start s, target ml, the simulated plant's true volume over the estimate); the estimate
#: ends 0.01 ml above the target.
STEPS = ((2.0, 30.0, 1.02), (6.0, 40.0, 0.97))
END_S = 10.0
#: The verified targets' scans: (time s, round, scanned ml); 30 ml within the 0.3 % asked at once, 40 ml in two.
SCANS = ((4.0, 1, 30.05), (7.5, 1, 38.9), (9.0, 2, 39.95))


def icosphere(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed sphere of 320 triangles (a subdivided icosahedron), counter-clockwise seen from outside."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    return np.asarray(sphere.vertices), np.asarray(sphere.faces)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return record_scene(tmp_path_factory.mktemp("report") / "run.rrd")


def record_scene(path):
    """A scene of two volume steps as the daemon records it: telemetry at 20 Hz, volumes (target, estimate, the
    simulated plant's true volume) at 5 Hz, the surface at 2 Hz growing with the volume, the scene's events."""
    rest, triangles = icosphere(20.0)
    recorder = Recorder(NAMES, save_path=path)
    recorder.open()
    recorder.log_rest_surface(rest, triangles)
    recorder.log_event(0.0, "model ready")
    volume_ml, target_ml, true_over_estimate = 26.3, None, 1.0
    for k in range(int(END_S * 20)):
        time_s = k / 20
        for index, (start_s, target, ratio) in enumerate(STEPS):
            if abs(time_s - start_s) < 1e-9:
                recorder.log_event(time_s, f"step {index} at {start_s - 2:g} s: {target:.2f} ml")
                target_ml, true_over_estimate = target, ratio
        if target_ml is not None:
            volume_ml += (target_ml + 0.01 - volume_ml) * 0.2
        true_ml = volume_ml * true_over_estimate
        pressures = np.full(3, (volume_ml - 26.3) / 8)
        recorder.log_telemetry(time_s, pressures, pressures + 0.01, [0.2, 0.4, 0.6])
        if k % 4 == 0:
            recorder.log_volumes(time_s, target_ml, volume_ml, [2.0, 2.0, 2.0], true_ml=true_ml)
        if k % 10 == 0:
            recorder.log_mesh(time_s, rest * (volume_ml / 26.3) ** (1 / 3), triangles)
        for scan_s, round_, scanned_ml in SCANS:
            if abs(time_s - scan_s) < 1e-9:
                recorder.log_scanned_volume(time_s, scanned_ml, round_, 0.3)
    recorder.log_event(END_S, "scene bph finished; holding its last target")
    recorder.close()
    return path


def test_the_report_reads_the_recording_back_steps_volumes_chambers_events(recording):
    run = load_run(recording)
    assert [chamber.name for chamber in run.chambers] == NAMES
    assert [chamber.colour for chamber in run.chambers] == [tuple(c / 255 for c in rgb) for rgb in CHAMBER_COLOURS[:3]]
    assert set(run.volumes) == {"commanded_ml", "estimated_ml", "true_ml", "scanned_ml"}
    assert [(step.index, step.start_s, step.end_s, step.target_ml) for step in run.steps] == [
        (0, 2.0, 6.0, 30.0), (1, 6.0, END_S, 40.0)]
    for step, (_, target, ratio) in zip(run.steps, STEPS, strict=True):
        assert step.estimate_ml == pytest.approx(target + 0.01, abs=0.02)
        assert step.true_ml == pytest.approx(step.estimate_ml * ratio, rel=1e-9)
        assert step.true_error_pct == pytest.approx((ratio - 1) * 100, abs=0.1)
    assert run.surfaces is not None and len(run.surfaces.time_s) == END_S * 2
    assert len(run.surfaces.positions_mm) == len(STEPS)  # only the surfaces pictured are read
    assert [event.text for event in run.events][0] == "model ready"
    assert [(scan.time_s, scan.round, scan.target_ml, scan.scanned_ml, scan.tolerance_pct) for scan in run.scans] == [
        (4.0, 1, 30.0, 30.05, 0.3), (7.5, 1, 40.0, 38.9, 0.3), (9.0, 2, 40.0, 39.95, 0.3)]
    for scan in run.scans:  # the true volume then: the last one logged at or before the scan
        assert scan.true_ml == run.volumes["true_ml"].at(scan.time_s)
        assert scan.error_pct == pytest.approx((scan.scanned_ml / scan.target_ml - 1) * 100)
    assert [[scan.round for scan in target] for target in verified_targets(run.scans)] == [[1], [1, 2]]


def test_scans_recorded_before_their_rounds_were_are_numbered_by_target():
    """A recording from before the daemon logged each scan's round and tolerance: a target's scans in a row are
    its rounds, a new target (or none) starts again at 1; nothing is judged against a tolerance not recorded."""
    def series(*rows):
        return Series(np.array([row[0] for row in rows], float), np.array([row[1] for row in rows], float))

    volumes = {"commanded_ml": series((0.0, 30.0), (10.0, 40.0), (20.0, 30.0)),
               "scanned_ml": series((5.0, 30.4), (6.0, 30.02), (12.0, 39.0), (14.0, 39.9), (16.0, 40.01),
                                    (22.0, 29.9))}
    scans = scans_in(volumes, {})
    assert [(scan.round, scan.target_ml, scan.true_ml, scan.tolerance_pct) for scan in scans] == [
        (1, 30.0, None, None), (2, 30.0, None, None), (1, 40.0, None, None), (2, 40.0, None, None),
        (3, 40.0, None, None), (1, 30.0, None, None)]
    assert [len(target) for target in verified_targets(scans)] == [2, 3, 1]
    assert "<td>-</td></tr>" in scans_table(scans) and "true ml" not in scans_table(scans)


@pytest.mark.slow  # seconds of numerics: make test, not make check
def test_the_html_holds_everything_inline_the_true_error_and_a_picture_per_step(recording, tmp_path):
    out = write_report(recording, tmp_path / "deep" / "report.html")
    text = out.read_text()
    assert "http" not in text.replace("http-equiv", ""), "the report must load nothing from elsewhere"
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', text)
    assert len(images) == 3 + 1 + len(STEPS)  # volume, scans, chambers, colour scale, one picture per step
    assert all(base64.b64decode(image).startswith(b"\x89PNG") for image in images)
    errors = [step.true_error_pct for step in load_run(recording).steps]
    assert "true error %" in text and all(f"<td>{error:+.2f}</td>" in text for error in errors)
    assert f"Mean |true error| {np.mean(np.abs(errors)):.2f} %" in text
    assert "scene bph finished" in text
    assert "3 scans of 2 verified targets, 1.5 rounds a target" in text
    # each scan judged against the tolerance its verification asked: 30.05 and 39.95 ml within 0.3 %, 38.9 not
    assert text.count("<td>yes (+-0.3 %)</td>") == 2 and text.count("<td>no (+-0.3 %)</td>") == 1


def test_a_recording_without_a_true_volume_or_surfaces_has_no_true_column_and_no_pictures(tmp_path):
    path = tmp_path / "board.rrd"
    recorder = Recorder(NAMES, save_path=path)
    recorder.open()
    for k in range(20):
        recorder.log_telemetry(k / 10, [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5])
        recorder.log_volumes(k / 10, 30.0, 29.9, [2.0, 2.0, 2.0])
    recorder.close()
    text = write_report(path, tmp_path / "board.html").read_text()
    assert "true" not in text.lower().replace("true error", "")
    assert "The gland</h2>" not in text


@pytest.mark.parametrize("content, message", [
    (None, "no such recording"),
    (b"not a recording at all", "cannot be read as a Rerun recording"),
])
def test_what_is_not_a_recording_is_refused_saying_what_to_give(tmp_path, content, message):
    path = tmp_path / "run.rrd"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(PhantomError, match=message):
        write_report(path, tmp_path / "run.html")
    assert not (tmp_path / "run.html").exists()


@pytest.mark.slow  # seconds of numerics: make test, not make check
def test_the_command_line_writes_the_report_beside_the_recording_by_default(recording, tmp_path):
    copy = tmp_path / "copy.rrd"
    shutil.copy(recording, copy)
    result = subprocess.run([sys.executable, "-m", "phantom.cli.main", "report", str(copy)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "copy.html").is_file() and "wrote" in result.stdout


def colour_pixels(png: np.ndarray, rgb: tuple[int, int, int], tolerance: int = 12) -> int:
    return int(np.all(np.abs(png[:, :, :3].astype(int) - np.asarray(rgb)) <= tolerance, axis=2).sum())


@pytest.mark.slow  # a browser starts (about 20 s)
@pytest.mark.skipif(shutil.which("chromium") is None, reason="needs Debian's chromium (apt-get install chromium)")
def test_headless_chromium_renders_the_plots_and_the_pictures(recording, tmp_path):
    """What a colleague sees: the page as Chromium draws it holds the volume plot's estimate and true lines, each
    chamber's colour and the pictures' colour map (viridis, from dark purple to yellow), not only text."""
    import matplotlib.image

    out = write_report(recording, tmp_path / "report.html")
    shot = tmp_path / "shot.png"
    subprocess.run(["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    "--window-size=1100,3000", f"--screenshot={shot}", out.as_uri()],
                   capture_output=True, timeout=120, check=True)
    png = (matplotlib.image.imread(shot) * 255).round().astype(np.uint8)
    estimate, true = (204, 121, 167), (0, 114, 178)
    for rgb in (estimate, true, *CHAMBER_COLOURS[:3]):
        assert colour_pixels(png, rgb, 20) > 100, f"colour {rgb} not drawn"
    scanned, tolerance_band = (0, 158, 115), (224, 243, 238)  # the scans' diamonds; the band, 12 % over white
    assert colour_pixels(png, scanned, 20) > 30, "the scans not drawn on the volume plot"
    assert colour_pixels(png, tolerance_band, 4) > 5000, "the tolerance asked not shaded on the scans' plot"
    viridis_ends = ((68, 1, 84), (253, 231, 37))  # the colour scale's ends
    for rgb in viridis_ends:
        assert colour_pixels(png, rgb, 20) > 100, f"the pictures' colour scale ({rgb}) not drawn"
    shaded = png[:, :, :3].astype(int)
    greenish = (shaded[:, :, 1] > shaded[:, :, 0] + 30) & (shaded[:, :, 1] > 60)
    assert greenish.sum() > 1000, "no gland picture drawn"
