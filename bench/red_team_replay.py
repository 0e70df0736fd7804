"""Replay the red team's attacks of issue 23 on a daemon and the simulated board, and print what held.

One daemon (``phantom daemon --port``, the calibrated model from its cached response table, recording to a
.rrd file) drives the simulated board (the real firmware in simavr, real time). In order:

    load              the stall bench's red-team load (bench/daemon_stall.py: 300 idle connections, 100
                      concurrent `surface`, a 30 MB and a 20,000-step scene, 50 clients flooding `status`)
                      while the daemon holds 32 ml: the board's link must survive, no fault may latch
    unplug            a scene plays (30, 38, 33, 36 ml at 0, 12, 24, 36 s); the board is unplugged from 8 s to
                      13 s, across step 1: the status must not claim step 1 while unplugged, and the board must
                      hold step 1's setpoints once it is back
    fault             a sensor fault latched from 20 s to 25 s, across step 2: the same promise, after
                      `clear_fault`
    worker kill       the model worker SIGKILLed (as the OOM killer does): `surface` and a new target must be
                      answered, and the restart counted in the status
    same recording    the daemon SIGKILLed and started again with the same --rerun-save (as systemd's
                      Restart=on-failure does): the first session's recording must survive whole; a second
                      daemon on another socket with the same path must be refused while the first lives

Each attack is bounded in count and time; all traffic is on the loopback Unix socket. The recording checks need
the issue-24 recording work (a new file per session, a held path refused): on a branch without it they fail.

    .venv/bin/python bench/red_team_replay.py [--log FILE]   # about 4 minutes; exit 1 if something did not hold
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
sys.path[:0] = [str(BENCH), str(BENCH.parent / "tests")]

import daemon_stall  # noqa: E402  (the bench's load, beside this script)
from daemon_rig import PHANTOM, DaemonRig, board_holds_solution, calibrated_scene  # noqa: E402

STEPS = [{"at_s": 0, "volume_ml": 30.0}, {"at_s": 12, "volume_ml": 38.0}, {"at_s": 24, "volume_ml": 33.0},
         {"at_s": 36, "volume_ml": 36.0}]


class Verdicts:
    """What held and what did not, printed as a table at the end."""

    def __init__(self) -> None:
        self.rows: list[tuple[str, str, bool, str]] = []

    def check(self, attack: str, promise: str, held: bool, detail: str = "") -> None:
        self.rows.append((attack, promise, bool(held), detail))
        print(f"{'held' if held else 'BROKEN'}: {attack}: {promise} {detail}", flush=True)

    def attempt(self, attack: str, promise: str, action: Any) -> Any:
        """Run ``action()``; a failure (an assertion, a timeout) is a broken promise, not the end of the replay."""
        try:
            return action()
        except Exception as error:  # the replay goes on to the next attack
            self.check(attack, promise, False, f"({type(error).__name__}: {str(error)[:300]})")
            return None

    def table(self) -> str:
        lines = ["| attack | promise | held | detail |", "|---|---|---|---|"]
        lines += [f"| {attack} | {promise} | {'yes' if held else 'NO'} | {detail} |"
                  for attack, promise, held, detail in self.rows]
        return "\n".join(lines)


def model_worker_pids(daemon_pid: int) -> list[int]:
    """The daemon's model worker processes (multiprocessing's spawned children; not its resource tracker)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            command = (entry / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if parent == daemon_pid and b"spawn_main" in command:
            found.append(int(entry.name))
    return found


def replay_load(rig: DaemonRig, verdicts: Verdicts) -> None:
    rig.call("set_target", {"volume_ml": 32.0})
    rig.wait_until(lambda: board_holds_solution(rig.status(), 32.0), 15, "holding 32 ml")
    before = rig.status()
    rows = asyncio.run(daemon_stall.main_async(rig.socket, rig.directory, "1,3,4,5,6"))
    after = rig.status()
    lost = after["link_detail"]["stats"]["links_lost"] - before["link_detail"]["stats"]["links_lost"]
    longest = max(row["loop_ms"] for row in rows)
    link_longest = max(row["link_ms"] or 0.0 for row in rows)
    verdicts.check("load", "the board's link survived, no fault latched", lost == 0 and not after["faults"],
                   f"(links lost {lost}, faults {after['faults'] or 'none'})")
    verdicts.check("load", "the link's loop stayed far inside the 500 ms dead-host deadline", link_longest < 250,
                   f"(longest stall: link's loop {link_longest:.0f} ms, daemon's loop {longest:.0f} ms; "
                   f"bare peer {max(row['peer_ms'] for row in rows):.0f} ms)")


def replay_unplug(rig: DaemonRig, verdicts: Verdicts) -> None:
    rig.wait_scene_time(8)
    rig.board.unplug()
    try:
        status = rig.wait_scene_time(13)
    finally:
        rig.board.replug()
    verdicts.check("unplug", "status does not claim step 1 while the board is away",
                   status["target_volume_ml"] == 38.0 and status["target_applied"] is False,
                   f"(target_pending: {status['target_pending']!r})")
    rig.wait_until(lambda: board_holds_solution(rig.status(), 38.0), 15, "step 1 held after the replug")
    verdicts.check("unplug", "the board holds step 1's setpoints once it is back", True)


def replay_fault(rig: DaemonRig, verdicts: Verdicts) -> None:
    rig.wait_scene_time(20)
    rig.board.inject("sensor_cut", chamber=1)
    rig.wait_until(lambda: "SENSOR_1" in rig.status()["faults"], 10, "the sensor fault latched")
    status = rig.wait_scene_time(25)
    verdicts.check("fault", "status does not claim step 2 while a fault is latched",
                   status["target_volume_ml"] == 33.0 and status["target_applied"] is False,
                   f"(target_pending: {status['target_pending']!r})")
    rig.board.inject("clear")
    cleared = rig.wait_until(lambda: rig.call("clear_fault"), 10, "the fault cleared (its cause gone)")
    rig.wait_until(lambda: board_holds_solution(rig.status(), 33.0), 10, "step 2 held after the clear")
    verdicts.check("fault", "clear_fault restores step 2, not step 1", cleared.get("target") == {"volume_ml": 33.0},
                   f"(answer target {cleared.get('target')})")


def replay_worker_kill(rig: DaemonRig, verdicts: Verdicts) -> None:
    pids = model_worker_pids(rig.process.pid)
    assert pids, "no model worker found under the daemon"
    for pid in pids:
        os.kill(pid, signal.SIGKILL)
    time.sleep(0.5)
    surface = rig.call("surface", timeout_s=120)
    rig.call("set_target", {"volume_ml": 34.0}, timeout_s=120)
    rig.wait_until(lambda: board_holds_solution(rig.status(), 34.0), 15, "34 ml held after the worker kill")
    status = rig.status()
    verdicts.check("worker kill", "surface and a new target answered by a new worker",
                   len(surface["positions_mm"]) > 0 and status["model_worker_restarts"] >= 1,
                   f"(model_worker_restarts {status['model_worker_restarts']})")


def replay_same_recording(rig: DaemonRig, verdicts: Verdicts, recording: Path) -> DaemonRig:
    # the second daemon drives a board of its own (--sim): the first one holds its port exclusively
    second = subprocess.Popen([str(PHANTOM), "daemon", "--sim", "--socket", str(rig.directory / "second.sock"),
                               "--rerun-save", str(recording)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
    try:
        output, _ = second.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        second.kill()
        output, _ = second.communicate(timeout=10)
    refused = second.returncode == 2 and str(recording) in output
    verdicts.check("same recording", "a second daemon with the live daemon's --rerun-save is refused", refused,
                   f"(exit {second.returncode}: {output.strip().splitlines()[-1][:200] if output.strip() else ''})")
    rig.process.send_signal(signal.SIGKILL)
    rig.process.wait(10)
    crashed_bytes = sum(path.stat().st_size for path in recording.parent.glob("*.rrd"))
    restarted = DaemonRig(rig.directory, "--rerun-save", str(recording), board=rig.board)
    restarted.wait_online()
    time.sleep(3.0)
    kept = sum(path.stat().st_size for path in recording.parent.glob("*.rrd") if path.stat().st_size)
    files = sorted(path.name for path in recording.parent.glob("*.rrd"))
    verdicts.check("same recording", "a restart with the same --rerun-save keeps the crashed session's recording",
                   kept >= crashed_bytes, f"({crashed_bytes} bytes before the restart; files now {files})")
    return restarted


def main() -> int:
    log_copy = Path(sys.argv[sys.argv.index("--log") + 1]) if "--log" in sys.argv else None
    verdicts = Verdicts()
    from phantom.hil.sim import SimulatedBoard

    with tempfile.TemporaryDirectory(prefix="phantom-red-team-") as folder, SimulatedBoard(speed=1.0) as board:
        directory = Path(folder)
        scene = directory / "replay_scene.toml"
        scene.write_text(calibrated_scene(STEPS, end_s=44))
        recording = directory / "recordings" / "run.rrd"
        rig = DaemonRig(directory, "--rerun-save", str(recording), board=board)
        try:
            rig.wait_online(120)
            verdicts.attempt("load", "the red-team load replayed", lambda: replay_load(rig, verdicts))
            started = verdicts.attempt("scene", "the scene started", lambda: rig.call("run_scene",
                                                                                     {"path": str(scene)}))
            if started is not None:
                verdicts.attempt("unplug", "the unplug replayed", lambda: replay_unplug(rig, verdicts))
                verdicts.attempt("fault", "the fault replayed", lambda: replay_fault(rig, verdicts))
            verdicts.attempt("worker kill", "the worker kill replayed", lambda: replay_worker_kill(rig, verdicts))
            rig = verdicts.attempt("same recording", "the restart replayed",
                                   lambda: replay_same_recording(rig, verdicts, recording)) or rig
        finally:
            rig.close()
            if log_copy is not None:
                log_copy.write_text((directory / "daemon.log").read_text())
    print()
    print(verdicts.table())
    return 0 if all(held for _, _, held, _ in verdicts.rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
