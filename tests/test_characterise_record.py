"""``phantom characterise --resume`` verifies its record before it stores anything from it (issue 51, item 3): a
row marked finished but never stored is stored only when its scan folder is this run's, its volume is that scan's
(reconstructed again), and its value is plausible (else stored unconfirmed); a record from another run or with a
design missing its keys is refused with why, never a KeyError."""

import json

import pytest
from test_characterise import _record
from test_corrections import _linear_grid

from phantom.cli import characterise as cli
from phantom.model.measurements import CorrectionStore
from phantom.scan.characterise import CharacterisationError, CharacterisationRecord, PointResult


def _row(record, index, volume_ml, pressures=None):
    pressures = list(record.points_kpa[index]) if pressures is None else pressures
    folder = record.scan_folder(index)
    folder.mkdir(parents=True, exist_ok=True)
    return PointResult(index, list(record.points_kpa[index]), pressures, volume_ml, 20.0 + 2.0 * sum(pressures),
                       str(folder.resolve()), "2026-11-27T11:00:00+00:00", 60.0)


def _scanned(volumes_ml):
    """The volume each scan folder reconstructs to (a stand-in for reconstruct: this layer's test)."""
    def volume_of(folder):
        return volumes_ml[int(folder.name)]
    return volume_of


def test_a_row_finished_but_never_stored_is_stored_only_with_its_scan_and_its_scans_volume(tmp_path):
    """The red team's record: point 0 (rest) marked finished with 40 ml, never stored; its scan reconstructs to
    20.1 ml. Before: stored blindly, and the daemon said 40 ml reached at 26.43 ml true. Now it is not stored and
    the point is scanned again; a row whose scan folder is gone likewise; a good row is stored."""
    record, store = _record(tmp_path / "run"), CorrectionStore(tmp_path / "store.json")
    record.finish(_row(record, 0, 40.0))
    record.finish(_row(record, 1, 22.3))
    missing = _row(record, 2, 22.0)
    record.finish(missing)
    record.scan_folder(2).rmdir()
    said = []
    cli._store_unstored(CharacterisationRecord.load(tmp_path / "run"), store, said.append, _linear_grid(),
                        _scanned({0: 20.1, 1: 22.3}))
    assert [e.volume_ml for e in store.entries()] == [22.3]
    again = CharacterisationRecord.load(tmp_path / "run")
    assert again.pending() == [0, 2], "the refused rows are scanned again"
    text = "\n".join(said)
    assert "point 0: not stored" in text and "40.000 ml" in text and "20.100 ml" in text
    assert "point 2: not stored" in text and "no scan folder" in text


def test_an_implausible_row_from_its_own_scan_is_stored_unconfirmed(tmp_path):
    record, store = _record(tmp_path / "run"), CorrectionStore(tmp_path / "store.json")
    record.finish(_row(record, 1, 30.0))       # the linear model says 22 ml at 1,0,0: +36 %
    cli._store_unstored(CharacterisationRecord.load(tmp_path / "run"), store, lambda text: None, _linear_grid(),
                        _scanned({1: 30.0}))
    (entry,) = store.entries()
    assert entry.status == "unconfirmed" and "expected 22.000 ml" in (entry.reason or "")
    assert store.confirmed() == []


def test_a_record_from_another_run_is_refused_with_why(tmp_path):
    other = _record(tmp_path / "other")
    other.finish(_row(other, 1, 22.3))
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "characterisation.json").write_text(other.path.read_text())   # copied from another run's folder
    with pytest.raises(CharacterisationError, match="not this run's .*from another run"):
        cli._store_unstored(CharacterisationRecord.load(mine), CorrectionStore(tmp_path / "s.json"), print,
                            _linear_grid(), _scanned({1: 22.3}))


@pytest.mark.parametrize(("change", "why"), [
    (lambda d: {**d, "design": {"kind": "grid"}}, "design has no values_kpa"),
    (lambda d: {**d, "design": {"kind": "grid", "values_kpa": "1,2"}}, "values_kpa must be a list of numbers"),
    (lambda d: {**d, "design": {"kind": "points", "count": 5}}, "design has no seed"),
    (lambda d: {**d, "design": {"kind": "magic"}}, "design's kind is one of grid, path, points"),
    (lambda d: json.dumps(d).replace('"phantom": ', '"phantom": "other", "phantom": ', 1), "duplicate key 'phantom'"),
    (lambda d: {**d, "results": [{**d["results"][0], "asked_kpa": [3.0, 3.0, 3.0]}]},
     "point 1 was asked at .* not the design's"),
])
def test_a_record_whose_design_or_rows_do_not_hold_together_is_refused_not_a_key_error(tmp_path, change, why):
    record = _record(tmp_path)
    record.finish(_row(record, 1, 22.3))
    changed = change(json.loads(record.path.read_text()))
    record.path.write_text(changed if isinstance(changed, str) else json.dumps(changed))
    with pytest.raises(CharacterisationError, match=why):
        CharacterisationRecord.load(tmp_path)

