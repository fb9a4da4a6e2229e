"""Where a sweep's points run: a local process pool (one thread per process), a Dask ``LocalCluster`` or a Dask
scheduler at an address; Ctrl-C is left to the parent, which stops the workers (an interrupt, SIGTERM included,
cancels the points not started and terminates the local workers, waiting ``STOP_WAIT_S`` before killing them).
Local workers die with their parent even when it is killed with SIGKILL (``_start_worker``)."""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import time
from concurrent.futures import ProcessPoolExecutor

from .model import SweepError, one_line

SCHEDULER_SCHEMES = ("tcp", "tls", "ucx", "ws", "wss")
CONNECT_TIMEOUT_S = 10
# one thread per worker process: the libraries' thread pools, and no helper thread for the next fluid step's
# momentum integrals (``VCYTO_PREFETCH``, ``sim.method.fluid``: 0 computes them in the step); idle OpenMP threads sleep
# at once, as in the command's own process (``vcyto.speedsettings.install``)
THREAD_VARIABLES = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                    "NUMBA_NUM_THREADS": "1", "VCYTO_PREFETCH": "0", "KMP_BLOCKTIME": "0"}
STOP_WAIT_S = 2.0               # how long terminated workers get to end before they are killed


@contextlib.contextmanager
def executor(scheduler: str | None, workers: int):
    """A concurrent.futures executor and its number of worker slots: a local process pool (``scheduler`` None),
    a Dask ``LocalCluster`` (``"local"``) or the Dask scheduler at an address. Local worker processes run one
    thread each (OMP/MKL/OpenBLAS/numba), as Dask's nannies do: parallelism is across points."""
    with _one_thread_per_process():
        if scheduler is None:
            with _process_pool(workers) as pool:
                yield pool, workers, f"{workers} local process{'es' if workers > 1 else ''}"
        else:
            with _dask_executor(scheduler, workers) as found:
                yield found


@contextlib.contextmanager
def _one_thread_per_process():
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    for name, value in THREAD_VARIABLES.items():
        os.environ.setdefault(name, value)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _start_worker(parent: int):
    """A local worker's start: Ctrl-C is left to the parent, which stops the workers, and the worker dies with its
    parent, even one killed with SIGKILL (which stops nothing): on Linux the kernel sends it SIGKILL when the
    parent goes (``PR_SET_PDEATHSIG``), elsewhere a watchdog thread sees that the parent changed."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if not _die_with_parent():
        import threading
        threading.Thread(target=_watch_parent, args=(parent,), name="vcyto-parent-watch", daemon=True).start()
    if os.getppid() != parent:            # the parent went before the worker could ask to follow it
        os._exit(1)


PR_SET_PDEATHSIG = 1                    # <linux/prctl.h>
PARENT_POLL_S = 0.5                     # the watchdog's interval where the kernel cannot be asked


def _die_with_parent() -> bool:
    """Ask Linux to kill this process when its parent ends; False where that cannot be asked."""
    import ctypes
    import sys
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent: int):
    while os.getppid() == parent:
        time.sleep(PARENT_POLL_S)
    os._exit(1)


@contextlib.contextmanager
def _interrupts_ignored():
    """Processes started within ignore Ctrl-C (an ignored signal stays ignored across exec): the parent stops them."""
    try:
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:                   # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def _process_pool(workers: int):
    before = set(multiprocessing.active_children())
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_start_worker, initargs=(os.getpid(),))
    try:
        yield pool
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)     # nothing more starts
        _stop(set(multiprocessing.active_children()) - before)
        raise
    else:
        pool.shutdown(wait=True)


def _stop(processes):
    """Terminate ``processes`` (a worker is mid-point: its chunk is lost, the finished ones are in the table), and
    kill those still there after ``STOP_WAIT_S``: none outlives the sweep."""
    for process in processes:
        process.terminate()
    deadline = time.monotonic() + STOP_WAIT_S
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join(STOP_WAIT_S)


def check_scheduler(address: str) -> str:
    """``address`` if it is ``local`` or a Dask address (tcp://, tls://, ucx://, ws://, wss:// HOST:PORT)."""
    from urllib.parse import urlsplit
    if address == "local":
        return address
    parts = urlsplit(address)
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme not in SCHEDULER_SCHEMES or not parts.hostname or port is None or parts.path not in ("", "/"):
        raise SweepError(f"--scheduler: {address!r} is not a Dask scheduler address; write tcp://HOST:PORT (tls:// for "
                         "an encrypted cluster) or 'local'")
    return address


def _connect(Client, scheduler: str):
    """A client of the scheduler at ``scheduler``, or an error within ``CONNECT_TIMEOUT_S``. A server that is not a
    Dask scheduler can answer with bytes that Dask reads as an absurd message length: that is a MemoryError here,
    reported as "cannot reach", not a crash."""
    import dask
    with dask.config.set({"distributed.comm.timeouts.connect": f"{CONNECT_TIMEOUT_S}s"}):
        return Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")


@contextlib.contextmanager
def _dask_executor(scheduler: str, workers: int):
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise SweepError("--scheduler: needs Dask: pip install 'vcyto[cluster]' (or pip install distributed)") from None
    cluster = None
    try:
        if scheduler == "local":
            with _interrupts_ignored():
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                                       silence_logs=logging.ERROR)
            client = Client(cluster)
        else:
            client = _connect(Client, scheduler)
    except (OSError, ValueError, MemoryError, TimeoutError) as error:
        if cluster is not None:
            cluster.close()
        raise SweepError(f"--scheduler: cannot reach a Dask scheduler at {scheduler} within {CONNECT_TIMEOUT_S} s "
                         f"({type(error).__name__}: {one_line(error)[:200]})") from None
    try:
        slots = max(1, sum(client.nthreads().values()))
        where = "a local Dask cluster" if cluster is not None else f"the Dask scheduler at {scheduler}"
        pool = client.get_executor(pure=False)
        yield pool, slots, f"{where} ({slots} worker threads)"
    except BaseException:
        if cluster is None:
            pool.shutdown(wait=False)    # cancels our points on a shared cluster; a LocalCluster just closes
        raise
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
