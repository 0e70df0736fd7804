"""The panel's presets (host/presets.py) and the daemon's refusals of a bad --http or [[presets]] at start: one line
on stderr, exit status 2, before anything slow."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import pytest

from phantom.host.api import ApiServer
from phantom.host.presets import DEFAULT_PRESETS, PresetError, check_presets, load_presets, shipped_scenes
from phantom.host.web import WebServer, panel_tokens, tell_panel_address

PHANTOM = Path(sys.executable).with_name("phantom")
CHAMBERS = ["chamber0", "chamber1", "chamber2"]
LABELS = ["base", "left lobe", "right lobe"]


def test_the_shipped_presets_are_targets_the_daemon_takes():
    check_presets(DEFAULT_PRESETS, CHAMBERS, LABELS)
    assert [preset.name for preset in DEFAULT_PRESETS] == ["normal", "symmetric BPH", "left lobe enlarged",
                                                          "right lobe enlarged"]
    assert DEFAULT_PRESETS[1].target == {"volume_ml": 44.0}
    assert all(preset.meaning for preset in DEFAULT_PRESETS)
    assert {scene["name"] for scene in shipped_scenes()} >= {"bph_growth", "lopsided"}
    assert all(Path(scene["path"]).is_absolute() for scene in shipped_scenes())


def test_a_config_files_presets_replace_the_shipped_ones(tmp_path):
    config = tmp_path / "phantomd.toml"
    config.write_text('[daemon]\nsim = true\n')
    assert load_presets(config) is None
    config.write_text('[daemon]\nsim = true\n\n[[presets]]\nname = "large"\nmeaning = "a 48 ml gland"\n'
                      'volume_ml = 48\n\n[[presets]]\nname = "lobes"\npressures_kpa = [0, 2, 2]\n')
    presets = load_presets(config)
    assert presets is not None and [(preset.name, preset.target) for preset in presets] == [
        ("large", {"volume_ml": 48}), ("lobes", {"pressures_kpa": [0, 2, 2]})]
    check_presets(presets, CHAMBERS, LABELS)


@pytest.mark.parametrize(("text", "words"), [
    ("presets = 3", "must be an array of tables"),
    ("[[presets]]\nvolume_ml = 30", "name must be a string"),
    ('[[presets]]\nname = "a"\nmeaning = 3\nvolume_ml = 30', "meaning must be a string"),
    ('[[presets]]\nname = "a"\nvolume_ml = 30\n[[presets]]\nname = "a"\nvolume_ml = 31', "named more than once: a"),
    ("[[presets]\n", "not valid TOML"),
])
def test_a_bad_presets_table_is_refused_with_what_is_wrong(tmp_path, text, words):
    config = tmp_path / "phantomd.toml"
    config.write_text(text)
    with pytest.raises(PresetError, match=words):
        load_presets(config)


@pytest.mark.parametrize(("target", "words"), [
    ({"volume_ml": -1}, "preset 'bad': volume_ml must be positive"),
    ({"volume_ml": 30, "pressures_kpa": [0, 0, 0]}, "give exactly one of"),
    ({"pressures_kpa": [1, 1]}, "must be a list of 3 numbers"),
    ({"volume_ml": 30, "colour": "red"}, "unknown key"),
])
def test_a_preset_the_phantom_cannot_take_is_refused(target, words):
    from phantom.host.presets import Preset

    with pytest.raises(PresetError, match=words):
        check_presets((Preset("bad", "", target),), CHAMBERS, LABELS)


def test_the_address_is_printed_with_a_one_time_code_only_at_a_terminal(tmp_path):
    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    tokens = panel_tokens(tmp_path / "panel-tokens.json")
    web = WebServer(ApiServer(tmp_path / "api.sock", {}), "127.0.0.1:8080", tokens)
    journal, terminal = io.StringIO(), Terminal()
    tell_panel_address(web, journal)
    tell_panel_address(web, terminal)
    assert tokens.control not in journal.getvalue() and str(tokens.path) in journal.getvalue()
    assert f"http://127.0.0.1:8080/?code={web.one_time_code}" in terminal.getvalue()
    assert tokens.control not in terminal.getvalue() and tokens.read not in terminal.getvalue()


@pytest.mark.parametrize(("arguments", "config", "words"), [
    (["--http", "localhost"], None, "--http 'localhost': give HOST:PORT"),
    (["--http", "0.0.0.0:0", "--no-http-token"], None, "reachable from other machines: it needs the token"),
    ([], '[daemon]\nsim = true\nhttp = "127.0.0.1:0"\n\n[[presets]]\nname = "x"\nvolume_ml = -2\n',
     "preset 'x': volume_ml must be positive"),
])
def test_the_daemon_refuses_a_bad_panel_at_start(tmp_path, arguments, config, words):
    command = [str(PHANTOM), "daemon", "--socket", str(tmp_path / "s.sock")]
    if config is not None:
        (tmp_path / "phantomd.toml").write_text(config)
        command += ["--config", str(tmp_path / "phantomd.toml")]
    else:
        command += ["--sim"]
    result = subprocess.run([*command, *arguments], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "PHANTOM_DATA_DIR": str(tmp_path / "data")})
    assert result.returncode == 2, result.stderr
    assert words in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "s.sock").exists()               # what it built was closed
