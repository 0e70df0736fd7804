"""More bad input to the daemon: a start-up scene (``--run-scene``) with a gland volume step beyond the reachable
range stops the start with one line, as ``run_scene`` refuses it at load; the panel's WebSocket refuses a JSON-RPC
request whose ``id`` is not a string, a number or null before it runs anything; ``phantom set`` checks its numeric
options against the daemon's bounds and names its flags.

The start-up check runs ``start_daemon`` with stand-ins for the model (no model built, no board); the WebSocket
check runs the panel's server in this process.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest
from test_scene_reachable import RANGE_ML, StandIns, bph_with

from phantom import PhantomError
from phantom.host.config import DaemonConfig
from phantom.model.scene import read_scene_toml

PHANTOM = Path(sys.executable).with_name("phantom")


# --- 1. phantom daemon --scene X --run-scene ----------------------------------------------------------------------

def start_with_stand_ins(monkeypatch, tmp_path: Path, scene: Path):
    """``start_daemon`` of ``--scene scene --run-scene`` with the model worker a stand-in whose inverse refuses
    gland volumes beyond :data:`RANGE_ML`: (the daemon or the PhantomError raised, the stand-ins, the socket)."""
    from dataclasses import replace

    from phantom.host import service

    parts = StandIns(scene)
    parts.model.info = replace(parts.model.info, scene_raw=read_scene_toml(scene), scene_path=str(scene))
    closed: list[str] = []
    parts.model.close = lambda: closed.append("model")
    parts.model.correction_event = lambda: ("correction", "none", "INFO")
    parts.closed = closed

    async def started(*args, **kwargs):
        return parts.model
    monkeypatch.setattr(service.ModelWorker, "start", started)
    socket = tmp_path / "d.sock"
    config = DaemonConfig(port=str(tmp_path / "no-board"), socket=str(socket), scene=str(scene), run_scene=True)

    async def start():
        try:
            daemon = await service.start_daemon(config)
        except PhantomError as error:
            return error
        await daemon.api.close()
        return daemon
    return asyncio.run(start()), parts, socket


def test_a_start_up_scene_beyond_the_reachable_range_stops_the_start_with_one_line(monkeypatch, tmp_path):
    scene = bph_with(tmp_path / "h_vol.toml", "volume_ml = 30", "volume_ml = 3000")
    error, parts, socket = start_with_stand_ins(monkeypatch, tmp_path, scene)
    assert isinstance(error, PhantomError), error  # before: the daemon started and played the scene
    said = str(error)
    assert "\n" not in said and "--run-scene" in said, said
    assert said.endswith("(the daemon was not started)") and "the scene was not started" not in said, said
    assert "steps[1] at 20 s asks 3000.00 ml" in said and f"{RANGE_ML[0]} to {RANGE_ML[1]} ml" in said, said
    assert parts.asked == [3000.0] and parts.commands == []
    assert parts.closed == ["model"] and not socket.exists()  # what was built is closed


def test_a_reachable_start_up_scene_starts(monkeypatch, tmp_path):
    scene = bph_with(tmp_path / "ok.toml", "volume_ml = 30", "volume_ml = 31")
    daemon, parts, _ = start_with_stand_ins(monkeypatch, tmp_path, scene)
    assert not isinstance(daemon, PhantomError), daemon
    assert parts.asked and parts.closed == []


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_phantom_daemon_run_scene_beyond_the_range_exits_2_with_one_line(tmp_path, default_model_cached):
    """On the real model worker, without a board: the start stops before the link is opened."""
    scene = bph_with(tmp_path / "h_vol.toml", "volume_ml = 30", "volume_ml = 3000")
    started = subprocess.run([str(PHANTOM), "daemon", "--port", str(tmp_path / "no-board"), "--socket",
                              str(tmp_path / "d.sock"), "--scene", str(scene), "--run-scene"],
                             capture_output=True, text=True, timeout=240)
    assert started.returncode == 2, started.stderr
    errors = [line for line in started.stderr.splitlines() if line.startswith("phantom daemon: error:")]
    assert errors == [started.stderr.strip().splitlines()[-1]] and "Traceback" not in started.stderr
    assert "steps[1] at 20 s asks 3000.00 ml" in errors[0] and "--run-scene" in errors[0], errors
    assert not (tmp_path / "d.sock").exists()


# --- 2. the panel's WebSocket: a JSON-RPC id that is not a string, a number or null -------------------------------

@pytest.mark.parametrize("request_id", ['{"a": 1}', "[1]", "true", "false", "NaN", "Infinity", "-Infinity"])
def test_a_request_whose_id_is_not_a_string_a_number_or_null_is_refused_before_it_runs(tmp_path, request_id):
    import json

    import aiohttp
    from test_web import panel_tokens, served

    from phantom.host.web import JSONRPC_CODES

    tokens = panel_tokens(tmp_path / "data" / "panel-tokens.json")
    ran: list[dict] = []

    async def vent(params):
        ran.append(params)
        return {"vented": True}

    async def test() -> None:
        async with served(tmp_path, tokens) as (api, web), aiohttp.ClientSession() as session:
            api.handlers["vent"] = vent
            url = f"http://127.0.0.1:{web.port}/websocket"
            async with session.ws_connect(url, headers={"Authorization": f"Bearer {tokens.control}"}) as socket:
                await socket.send_str(f'{{"jsonrpc": "2.0", "id": {request_id}, "method": "vent"}}')
                answer = json.loads((await socket.receive(timeout=5)).data)  # valid JSON: no NaN echoed
                assert answer["id"] is None and answer["error"]["code"] == JSONRPC_CODES["invalid_request"] == -32600
                assert "id" in answer["error"]["message"] and "string, a number or null" in answer["error"]["message"]
                # the valid ids are answered with themselves, and the method runs for them
                for good in ["7", '"seven"', "null", "2.5", str(10**30)]:
                    await socket.send_str(f'{{"jsonrpc": "2.0", "id": {good}, "method": "vent"}}')
                    answer = json.loads((await socket.receive(timeout=5)).data)
                    assert answer == {"jsonrpc": "2.0", "id": json.loads(good), "result": {"vented": True}}
        assert len(ran) == 5  # never for the invalid id (before: it vented, answered with id null)
    asyncio.run(test())


# --- 3. phantom set's numeric options are checked before connecting, naming the flags -------------------------------

@pytest.mark.parametrize("options, words", [
    (["--volume-ml", "32", "--wait", "--tolerance-pct", "-1"], "--tolerance-pct must be a number more than 0"),
    (["--volume-ml", "32", "--wait", "--tolerance-pct", "nan"], "--tolerance-pct must be a number more than 0"),
    (["--volume-ml", "32", "--wait", "--tolerance-pct", "101"], "--tolerance-pct must be a number more than 0"),
    (["--volume-ml", "32", "--wait", "--timeout-s", "0"], "--timeout-s must be a positive number of seconds"),
    (["--volume-ml", "32", "--wait", "--timeout-s", "inf"], "--timeout-s must be a positive number of seconds"),
    (["--volume-ml", "32", "--verify", "scan", "--verify-tolerance-pct", "0.01"], "--verify-tolerance-pct must be"),
    (["--volume-ml", "32", "--verify", "scan", "--verify-tolerance-pct", "nan"], "--verify-tolerance-pct must be"),
    (["--volume-ml", "32", "--verify", "scan", "--verify-rounds", "0"], "--verify-rounds must be a whole number"),
    (["--volume-ml", "32", "--verify", "auto", "--verify-rounds", "1000"], "--verify-rounds must be a whole number"),
    (["--volume-ml", "nan"], "--volume-ml must be a number of at least"),
    (["--volume-ml", "-3"], "--volume-ml must be a number of at least"),
    (["--chamber-volumes-ml", "0,1,1"], "--chamber-volumes-ml: each volume must be at least"),
    (["--chamber-volumes-ml=-,-,-"], "--chamber-volumes-ml needs at least one number"),
])
def test_set_checks_its_numeric_options_before_connecting_and_names_the_flag(options, words):
    """Before: the daemon's refusal named its params (``set_target: tolerance_pct (...)``)."""
    from phantom.cli.main import build_parser
    from phantom.host.scenes import MIN_VOLUME_ML
    from phantom.host.verify import MAX_VERIFY_ROUNDS, VERIFY_TOLERANCE_PCT

    args = build_parser().parse_args(["set", *options, "--socket", "/nonexistent/d.sock"])
    with pytest.raises(PhantomError) as caught:
        args.run(args)
    said = str(caught.value)
    assert words in said and "\n" not in said and "_pct" not in said and "_ml" not in said, said
    if "--verify-tolerance-pct" in words:
        assert f"from {VERIFY_TOLERANCE_PCT[0]:g} to {VERIFY_TOLERANCE_PCT[1]:g}" in said
    if "--verify-rounds" in words:
        assert f"from 1 to {MAX_VERIFY_ROUNDS}" in said
    if "-ml" in words and "needs" not in words:
        assert f"{MIN_VOLUME_ML:g} ml" in said


@pytest.mark.parametrize("options", [
    ["--volume-ml", "32", "--wait", "--tolerance-pct", "100", "--timeout-s", "0.5"],
    ["--volume-ml", "32", "--verify", "scan", "--verify-tolerance-pct", "20", "--verify-rounds", "10"],
    ["--chamber-volumes-ml=-,2,2"],
])
def test_set_options_within_the_bounds_go_to_the_daemon(options):
    from phantom.cli.main import build_parser

    args = build_parser().parse_args(["set", *options, "--socket", "/nonexistent/d.sock"])
    with pytest.raises(PhantomError, match="no daemon is listening on /nonexistent/d.sock"):
        args.run(args)
