"""Building the daemon's parts and running it: :func:`run_daemon` (what ``phantom daemon`` calls).

:func:`start_daemon` builds every part in an order that never harms another daemon: the API's socket first (a
second daemon stops there, before it opens anything of the first's), the recording (a path another daemon records
to, or one that cannot be written, is refused before anything slow), the model in its worker process, the
simulated board if any, the link session; then the :class:`phantom.host.daemon.Daemon` that drives them, and its
API handlers. A start that fails closes what it built.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import signal
from collections.abc import Callable
from typing import Any

from phantom import PhantomError
from phantom.host.api import ApiError, ApiServer, Handler, default_socket_path
from phantom.host.config import DaemonConfig
from phantom.host.daemon import PA_PER_KPA, Daemon, VerifyScanner
from phantom.host.handlers import ApiHandlers
from phantom.host.link_process import LinkProcess
from phantom.host.logs import configured_level
from phantom.host.model_worker import ModelWorker
from phantom.host.motion import Scanner, scan_method
from phantom.host.presets import DEFAULT_PRESETS, Preset, check_presets, preset_method
from phantom.host.recording import Recorder
from phantom.host.scene_runner import prepare_run
from phantom.host.scenes import read_timeline_scene
from phantom.host.session import LinkTiming, Transport
from phantom.host.sim_board import SimulatedBoardFactory, SimulatedBoardKeeper
from phantom.host.stalls import GC_PAUSES
from phantom.host.startup import StartupProgress, notify_systemd
from phantom.host.transports import CanTransport, SerialTransport
from phantom.host.web import WebServer, panel_tokens, tell_panel_address
from phantom.model.errors import SceneError
from phantom.protocol.link import BOOT_DELAY_S, board_host_deadline_ms

logger = logging.getLogger(__name__)

#: File mode of the API's socket: the owner and the group may drive the phantom.
SOCKET_MODE = 0o660
#: How long the shutdown waits for the scans being stored as measurements (the correction's fit, s).
STORE_WAIT_S = 60.0
#: The methods that need the board: before the daemon is first ready they answer ``starting`` (with its progress).
BOARD_METHODS = ("set_target", "run_scene", "zero", "clear_fault")


async def start_daemon(config: DaemonConfig, simulated_board: SimulatedBoardFactory | None = None,
                       presets: tuple[Preset, ...] = DEFAULT_PRESETS) -> Daemon:
    """Build every part, in an order that never harms another daemon; raises PhantomError (one line).
    ``simulated_board`` builds the board of ``config.sim`` (the command line passes the HIL package's); ``presets``
    are the panel's buttons (the config file's ``[[presets]]``)."""
    if config.sim and simulated_board is None:
        raise PhantomError("this program cannot simulate a board: start the daemon with `phantom daemon --sim`")
    startup = StartupProgress()
    api = ApiServer(config.socket or default_socket_path(), {}, mode=SOCKET_MODE)
    api.starting = lambda: ApiError("starting", f"the daemon is still starting: {startup.text()}",
                                    startup.to_json())
    await api.start()  # first: a second daemon stops here, before it opens anything of the first's
    early: list[tuple[str, str, str]] = []  # what the parts say before the daemon exists
    closers: list[Callable[[], None]] = []
    web = None
    try:
        if config.http:  # the panel's port, taken or not, is known before anything slow
            web = WebServer(api, config.http, panel_tokens() if config.http_token else None,
                            tuple((config.http_hosts or "").split(",")))
            await web.start()
        # the recording opens before the model is built: a path another daemon records to, or one that
        # cannot be written, is refused before anything slow
        startup.enter("opening the recording")
        timeline = read_timeline_scene(config.scene)
        _check_pressure_limit(config, timeline.scene.model_settings.pressure_max_pa / PA_PER_KPA)
        early.append(("startup", f"playing {timeline.describe(config.scene)}", "INFO"))
        recorder = Recorder(timeline.scene.chamber_labels, config.rerun_save, config.rerun_connect,
                            on_problem=lambda text, level: early.append(("recording", text, level)))
        recorder.open()
        closers.append(recorder.close)
        startup.enter(f"loading the model of {config.scene}")
        model = await ModelWorker.start(config.scene, configured_level(), defer_table=True, phantom=config.phantom,
                                        on_message=startup.tell)
        closers.append(model.close)
        check_presets(presets, model.info.chamber_names, model.info.chamber_labels)  # the buttons' targets
        early.append(model.correction_event())
        sim_board = None
        if simulated_board is not None and config.sim:
            sim_board = SimulatedBoardKeeper(config.sim_speed, lambda *said: early.append(said), simulated_board)
            closers.append(sim_board.close)
            startup.enter(f"starting the simulated board (firmware in simavr, speed {config.sim_speed:g})")
            await asyncio.get_running_loop().run_in_executor(None, sim_board.start)
        session = _link_session(config, sim_board)
        daemon = Daemon(config, api, model, recorder, session, sim_board, startup=startup)
        if config.run_scene:  # a volume step beyond the reachable range stops the start, as run_scene refuses it
            await _check_start_up_scene(daemon)
    except BaseException:
        for close in reversed(closers):
            with contextlib.suppress(Exception):
                close()
        if web is not None:
            await web.close()
        await api.close()
        raise
    daemon.web = web
    recorder.on_problem = lambda text, level: daemon.event("recording", text, level)
    if sim_board is not None:
        sim_board.on_event = daemon.event
    session.attach(on_telemetry=daemon.on_telemetry, on_event=daemon.event, on_online=daemon.on_online,
                   on_motion=daemon.motion.on_message)
    for said in early:
        daemon.event(*said)
    handlers = ApiHandlers(daemon).table()
    for name in BOARD_METHODS:
        handlers[name] = _when_ready(daemon, handlers[name])
    handlers.update(preset_method(daemon, presets))
    api.handlers.update(handlers)
    api.handlers.update(daemon.motion.api_methods())
    startup.enter("waiting for the board: the first connection")
    return daemon


def _check_pressure_limit(config: DaemonConfig, pressure_max_kpa: float) -> None:
    """The board's over-pressure limit must let through every pressure the model may set (up to its scene's
    ``pressure_max_kpa``): below it, the board refuses each setpoint above the limit, targets the daemon says it
    reaches among them."""
    if config.pressure_limit_kpa < pressure_max_kpa:
        raise PhantomError(f"the pressure limit ({config.pressure_limit_kpa:g} kPa) is below the scene "
                           f"{config.scene}'s pressure_max_kpa ({pressure_max_kpa:g} kPa), up to which the model sets "
                           f"pressures: give --pressure-limit-kpa (or pressure_limit_kpa in the config file) of at "
                           f"least {pressure_max_kpa:g}, or a scene with a lower [model] pressure_max_kpa")


async def _check_start_up_scene(daemon: Daemon) -> None:
    """``--run-scene``'s scene is checked as ``run_scene`` checks one at load (:meth:`Daemon.check_scene_reachable`):
    a gland volume step beyond the reachable range raises PhantomError (one line) naming the step and the range.
    A scene whose steps are not valid is left to :func:`serve`, which says why it was not started."""
    info = daemon.model.info
    try:
        prepared = prepare_run(info.scene_raw, info.scene_path, daemon.chamber_names, 1.0, info.wants_shape)
    except SceneError:
        return
    try:
        await daemon.check_scene_reachable(prepared)
    except ApiError as error:
        raise PhantomError(f"--run-scene: {error} (the daemon was not started)") from None


def _when_ready(daemon: Daemon, handler: Handler) -> Handler:
    """``handler``, answering ``starting`` with the start-up's progress until the daemon is first ready."""
    async def guarded(params: dict[str, Any]) -> object:
        if not daemon.ready:
            link = daemon.session.state.value
            raise ApiError("starting", f"the daemon is still starting: {daemon.startup.text()}; the link is {link}",
                           {**daemon.startup.to_json(), "link": link})
        return await handler(params)
    return guarded


def _link_session(config: DaemonConfig, sim_board: SimulatedBoardKeeper | None) -> LinkProcess:
    """The link session over the configured transport, in a process of its own at a real-time priority where it
    may have one (its callbacks attached once the daemon is built)."""
    transport: Transport
    boot_delay_s = 0.0
    if config.can_channel:
        transport = CanTransport(config.can_channel, config.can_interface)
    elif sim_board is not None:
        transport = SerialTransport(sim_board.port, config.baud)
        boot_delay_s = BOOT_DELAY_S["sim"]
    else:
        assert config.port is not None  # a DaemonConfig has exactly one board
        transport = SerialTransport(config.port, config.baud)
        boot_delay_s = max(BOOT_DELAY_S.values()) if config.boot_delay_s is None else config.boot_delay_s
    return LinkProcess(transport, link_timing(config, boot_delay_s), config.link_rt_priority or None)


def link_timing(config: DaemonConfig, boot_delay_s: float) -> LinkTiming:
    """The link's periods and deadlines: the configured ones in wall-clock time, on a simulated board at its speed
    too."""
    # a simulated board faster than real time passes its dead-host deadline sooner (speed 0: as fast as it can,
    # about 5x here); a HELLO whose reply was lost must be repeated before that deadline: HELLOs go out at twice
    # the keepalive period. The deadline itself is the configured one in wall-clock time, as a real board's: in
    # board time it was half of it at --sim-speed 2, and a verified target's scan, reconstructed in a thread of
    # the daemon's process while the tests loaded both cores, held the link (then a thread) past it (DEAD_HOST)
    speed = (config.sim_speed or 10.0) if config.sim else 1.0
    return LinkTiming(keepalive_s=min(0.1, 0.1 / speed), hello_timeout_s=min(0.2, 0.2 / speed),
                      telemetry_period_ms=config.telemetry_period_ms,
                      host_deadline_ms=board_host_deadline_ms(config.host_deadline_ms, speed),
                      boot_delay_s=boot_delay_s)


async def serve(daemon: Daemon) -> int:
    """Run the tasks until SIGTERM/SIGINT or :meth:`Daemon.request_stop`, then vent and close; the exit code."""
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, daemon.request_stop)
    loop.set_exception_handler(_log_loop_exception)
    GC_PAUSES.install()
    try:
        info = daemon.model.info
        daemon.event("startup", "model ready: " + ", ".join(f"{key} {value:.2f} s"
                                                         for key, value in info.timings_s.items()))
        daemon.tasks = [asyncio.create_task(daemon.session.run(), name="link"),
                       asyncio.create_task(daemon._control_loop(), name="control"),
                       asyncio.create_task(daemon.loop_stalls.probe(), name="event loop probe")]
        if info.pending_fidelity is not None:
            daemon.table.start()
        if daemon.sim_board is not None:
            daemon.tasks.append(asyncio.create_task(daemon.sim_board.watch(), name="simulated board"))
        for task in daemon.tasks:
            task.add_done_callback(functools.partial(_task_ended, daemon))
        logger.info("serving: API on %s, board on %s", daemon.api.socket_path, daemon.session.transport.description)
        if daemon.config.run_scene:
            try:
                daemon.start_scene(prepare_run(info.scene_raw, info.scene_path, daemon.chamber_names, 1.0,
                                             info.wants_shape))
            except SceneError as error:
                daemon.event("scene", f"the scene's [[steps]] were not started: {error}", "ERROR")
        await daemon.stopping.wait()
    finally:
        await _shutdown(daemon)
    return daemon.exit_code

def _task_ended(daemon: Daemon, task: asyncio.Task[Any]) -> None:
    """A main task must run until shutdown: one that failed is a bug, logged with its traceback, and the
    daemon stops (exit status 1; under systemd it is restarted)."""
    if task.cancelled() or daemon.stopping.is_set():
        return
    error = task.exception()
    logger.error("the %s task ended unexpectedly", task.get_name(), exc_info=error)
    daemon.event("internal", f"the {task.get_name()} task ended: {type(error).__name__}: {error}", "ERROR")
    daemon.exit_code = 1
    daemon.request_stop()


async def _shutdown(daemon: Daemon) -> None:
    """Vent the phantom (if the board is there), close the recording, the API, the link and the model."""
    logger.info("stopping: venting and closing")
    venting = daemon.config.vent_on_exit and daemon.session.online
    if venting:  # first: a target waited on (a verified one's scan too) ends told it was vented, as it is
        with contextlib.suppress(TimeoutError, ApiError):  # the core's event says why
            await asyncio.wait_for(daemon.vent("on shutdown"), 2.0)
    await daemon.motion.stop_scan("the daemon is stopping")  # its capture ends, marked stopped, drivers released
    if daemon.storing:  # a verified target's last scan is stored as its outcome is told: kept, not cancelled
        logger.info("stopping: storing %d scan(s) as measurements first", len(daemon.storing))
        await asyncio.wait(set(daemon.storing), timeout=STORE_WAIT_S)
    if venting:
        # the board's session ends, so that it does not latch DEAD_HOST once the daemon is gone
        if await daemon.session.end_session():
            daemon.event("link", "session ended: the board is vented and expects no host")
        else:
            daemon.event("link", "the board did not answer the end of its session: it will latch DEAD_HOST",
                       "WARN")
    notify_systemd("STOPPING=1")
    daemon.session.stop()
    daemon.table.stop()
    for task in [*daemon.tasks, *daemon.background]:
        task.cancel()
    for task in [*daemon.tasks, *daemon.background]:
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
    if daemon.web is not None:
        await daemon.web.close()
    await daemon.api.close()
    daemon.recorder.log_event(daemon.now_s(), "daemon stopped")
    daemon.recorder.close()
    if daemon.sim_board is not None:
        await asyncio.get_running_loop().run_in_executor(None, daemon.sim_board.close)
    daemon.model.close()


def _log_loop_exception(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
    """Errors the event loop catches (a background task's exception nobody awaited) go to the log with their
    traceback."""
    logger.error("unexpected error: %s", context.get("message", "in the event loop"), exc_info=context.get("exception"))


async def _run(config: DaemonConfig, simulated_board: SimulatedBoardFactory | None,
               scanner: Scanner | None = None, verify_scanner: VerifyScanner | None = None,
               presets: tuple[Preset, ...] = DEFAULT_PRESETS) -> int:
    # SIGTERM or SIGINT while the parts are built (a first start builds the response table for minutes) cancels
    # the build: the parts built so far are closed and the model worker is ended with the processes it started
    loop = asyncio.get_running_loop()
    starting = asyncio.current_task()
    assert starting is not None
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, starting.cancel)
    try:
        daemon = await start_daemon(config, simulated_board, presets)
    except asyncio.CancelledError:
        logger.info("stopped while starting")
        return 0
    if daemon.web is not None:
        tell_panel_address(daemon.web)
    if scanner is not None:
        daemon.api.handlers.update(scan_method(daemon.motion, scanner, daemon.status))
        daemon.verify_scanner = verify_scanner
    return await serve(daemon)


def run_daemon(config: DaemonConfig, simulated_board: SimulatedBoardFactory | None = None,
               scanner: Scanner | None = None, verify_scanner: VerifyScanner | None = None,
               presets: tuple[Preset, ...] = DEFAULT_PRESETS) -> int:
    """Run the daemon in this process until SIGTERM/SIGINT; returns the exit status. ``simulated_board`` builds
    the board of ``config.sim``; ``scanner`` takes the ``scan`` API method's captures (host/motion.py);
    ``verify_scanner`` reconstructs a verified target's scans (host/daemon.py); ``presets`` are the panel's
    buttons."""
    return asyncio.run(_run(config, simulated_board, scanner, verify_scanner, presets))
