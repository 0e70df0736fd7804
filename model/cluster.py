"""Dask, the one engine that spreads the model's independent solves: the response table's grid points
(:mod:`phantom.model.fidelity.response_table`, also the simulated board's truth table) and the calibration's
pressure rays (:mod:`phantom.model.calibration.sweep`).

:func:`dask_client` gives a client of an existing cluster (``scheduler="tcp://host:port"``, or Dask's own
``DASK_SCHEDULER_ADDRESS`` / ``scheduler-address`` setting when none is given), else of a LocalCluster of
single-threaded worker processes on this machine's cores, closed after the work. A worker lost mid-task (killed,
out of memory) is no error: the scheduler runs its tasks again on another worker, and recomputes the results
that were held only there from the tasks that made them. :func:`stderr_progress` shows how the work goes and how
long it has left.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

from phantom import PhantomError, require_extra

if TYPE_CHECKING:
    from dask.distributed import Client, LocalCluster

#: ``progress(done, total)``: how a build or a sweep goes.
Progress = Callable[[int, int], None]


class ClusterError(PhantomError):
    """No Dask cluster to run on: no scheduler answers at the address given, or the local workers did not start."""


class LocalWorkersError(ClusterError):
    """The LocalCluster's worker processes did not start (a spawned worker re-runs the calling script: one
    without ``if __name__ == "__main__":`` kills it); the work can still be done in the calling process."""


def local_cluster(n_workers: int | None = None) -> LocalCluster:
    """A LocalCluster of single-threaded worker processes (default: one per core), quiet, dashboard on a free port."""
    # dask.distributed (1 s to import, an optional extra) only where solves are spread
    with require_extra("calibrate"):
        from dask.distributed import LocalCluster

    logging.getLogger("distributed").setLevel(logging.ERROR)
    # each worker process runs this module's dask_setup first: it dies with the process that made the cluster
    return LocalCluster(n_workers=n_workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                        dashboard_address=":0", silence_logs=logging.ERROR, preload=[__name__])


#: Linux prctl option: the signal a process gets when its parent dies (prctl(2)).
PR_SET_PDEATHSIG = 1


def exit_with_parent(parent_pid: int, signum: signal.Signals = signal.SIGKILL) -> None:
    """In a child process: get ``signum`` (SIGKILL: be killed) when the parent dies, however it dies (SIGKILL
    included): Linux's PR_SET_PDEATHSIG through libc; if the parent died before this ran, exit now. The one hook
    of every helper process the project starts (the daemon's model worker and API server, Dask's local workers,
    the simulated phantom's shape solver), so that none outlives a killed parent, solving for nobody."""
    import ctypes
    import ctypes.util

    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(signum), 0, 0, 0) != 0:
        logging.getLogger(__name__).warning("prctl(PR_SET_PDEATHSIG) failed (errno %d): this helper process may "
                                            "outlive a killed parent", ctypes.get_errno())
    if os.getppid() != parent_pid:
        os._exit(0)


def dask_setup(worker: object) -> None:
    """Dask's preload hook, in each worker process of :func:`local_cluster`: be killed when the process that made
    the cluster (a daemon's model worker, ``phantom model table``) dies, however it dies. Its nannies live in that
    process and the workers are its children, so a SIGKILLed builder left them running, solving for nobody."""
    exit_with_parent(os.getppid())


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, n_workers: int | None = None) -> Iterator[Client]:
    """A client of the scheduler at ``scheduler`` (else Dask's configured ``scheduler-address``), or of a
    LocalCluster of ``n_workers`` processes (default: the cores) that is closed with the client."""
    with require_extra("calibrate"):
        import dask
        from dask.distributed import Client

    address = scheduler or dask.config.get("scheduler-address", None)
    cluster = None
    if address:
        try:
            client = Client(address, timeout="5s")
        except (OSError, TimeoutError) as error:
            raise ClusterError(f"no Dask scheduler answers at {address} ({error}): start one (dask scheduler, "
                               f"then dask worker {address} on each machine) or leave --scheduler out for a "
                               f"cluster on this machine's cores") from None
    else:
        try:
            cluster = local_cluster(n_workers)
        except RuntimeError as error:  # distributed's "Nanny failed to start."
            raise LocalWorkersError(f"the worker processes could not start ({error}): does the calling script "
                                    f"guard its code with if __name__ == '__main__':?") from None
        client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def stderr_progress(label: str) -> Progress:
    """A progress callback that redraws ``label [#####.....] done/total, elapsed, time left`` on stderr; the
    time left is the work left at the rate of this run (work found done at the start, a resumed build's, is
    not counted in the rate)."""
    started = time.monotonic()
    first_done: list[int] = []

    def report(done: int, total: int) -> None:
        if not first_done:
            first_done.append(done)
        elapsed_s = time.monotonic() - started
        width = 30
        filled = int(width * done / max(total, 1))
        rate = (done - first_done[0]) / elapsed_s if elapsed_s > 0 else 0.0
        left = f", about {(total - done) / rate:.0f} s left" if rate > 0 and done < total else ""
        sys.stderr.write(f"\r{label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total} "
                         f"{elapsed_s:.0f} s{left}  ")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()
    return report
