"""One small interface for tile-pair work: a local process pool, or a Dask cluster.

Jobs are small picklable records (file paths, windows, cameras), never image arrays: each worker
reads the windows it needs from the GeoTIFFs, so no process holds a copy of a whole image.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Callable, Iterable, Iterator


def _init_worker(parent_pid: int | None = None) -> None:
    """Two cores shared by several processes: one thread per library inside each worker; and
    the worker ends itself when the process that started the pool is gone (killed with -9, say):
    forkserver workers are not its children, so nothing else would end them."""
    import signal

    # Ctrl-C reaches the whole process group: the parent shuts the pool down and sweeps its
    # scratch; a worker interrupted mid-job would only print a traceback after "interrupted"
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    import cv2

    cv2.setNumThreads(1)
    if parent_pid is not None:
        threading.Thread(target=_exit_with, args=(parent_pid,), daemon=True,
                         name="aerec-parent-watch").start()


def _exit_with(pid: int, period_s: float = 1.0) -> None:
    while True:
        time.sleep(period_s)
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            os._exit(1)
        except PermissionError:          # alive, owned by someone else (cannot be ours)
            pass


class Executor:
    """map_unordered(fn, jobs) yields fn(job) results as they finish."""

    def map_unordered(self, fn: Callable, jobs: Iterable) -> Iterator:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class SerialExecutor(Executor):
    def map_unordered(self, fn, jobs):
        for job in jobs:
            yield fn(job)


class LocalExecutor(Executor):
    """A process pool with at most `workers` jobs in flight (bounded memory)."""

    def __init__(self, workers: int | None = None):
        self.workers = workers or max(1, os.cpu_count() or 1)
        # Never fork: a forked child inherits OpenCV's and GDAL's thread state and can deadlock.
        ctx = multiprocessing.get_context("forkserver")
        self.pool = ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=_init_worker,
                                        initargs=(os.getpid(),))

    def map_unordered(self, fn, jobs):
        jobs = iter(jobs)
        pending = set()
        for job in jobs:
            pending.add(self.pool.submit(fn, job))
            if len(pending) >= 2 * self.workers:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    yield f.result()
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                yield f.result()

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


WORKER_POLL_S = 10.0        # how often a distributed run waiting on its jobs asks for workers
NO_WORKER_WARN_S = 60.0     # a scheduler without a worker this long: said
NO_WORKER_GIVE_UP_S = 600.0  # ... and this long: the run ends with an error


class DaskExecutor(Executor):
    """Sends jobs to a dask.distributed scheduler (as CNES CARS does for production DSMs).

    While it waits for results it watches the scheduler's workers: with none for
    NO_WORKER_WARN_S it says so (`on_wait`), and with none for NO_WORKER_GIVE_UP_S it ends the
    run with an error, instead of waiting for ever on work no one will do."""

    def __init__(self, address_or_client, on_wait=None, warn_s: float = NO_WORKER_WARN_S,
                 give_up_s: float = NO_WORKER_GIVE_UP_S, poll_s: float = WORKER_POLL_S):
        try:
            from distributed import Client
        except ImportError as exc:  # pragma: no cover - depends on the optional extra
            raise RuntimeError("--scheduler needs dask.distributed: pip install 'aerec[dask]'") from exc
        self._own = not isinstance(address_or_client, Client)
        self.client = Client(address_or_client) if self._own else address_or_client
        self.on_wait = on_wait
        self.warn_s, self.give_up_s, self.poll_s = warn_s, give_up_s, poll_s

    def _workers(self) -> int:
        try:
            return len(self.client.scheduler_info().get("workers", {}))
        except Exception:                      # the scheduler itself gone: no worker either
            return 0

    def map_unordered(self, fn, jobs):
        from distributed import TimeoutError as DaskTimeout
        from distributed import as_completed

        from recon_core.errors import ReconstructionError

        futures = [self.client.submit(fn, job, pure=False) for job in jobs]
        yielded: set = set()

        def waiting():
            # as_completed's timeout runs from when it was made: it is made again at every poll,
            # over the futures not yielded yet (a future done but not yet yielded stays in it)
            return as_completed([f for f in futures if f.key not in yielded], timeout=self.poll_s)
        pending = waiting()
        alone_since, told = None, False
        while len(yielded) < len(futures):
            left = len(futures) - len(yielded)
            try:
                fut = next(pending)
            except DaskTimeout:
                if self._workers() > 0:
                    alone_since, told = None, False
                    pending = waiting()
                    continue
                alone_since = alone_since or time.monotonic()
                alone = time.monotonic() - alone_since
                if alone >= self.give_up_s:
                    for f in futures:
                        f.cancel()
                    assert self.client.scheduler is not None     # connected
                    raise ReconstructionError(
                        f"the Dask scheduler {self.client.scheduler.address} has had no worker for "
                        f"{alone:.0f} s with {left} dense job(s) left: none came back; start "
                        "`dask worker ADDRESS` and run again (finished stages are kept)") from None
                if alone >= self.warn_s and not told and self.on_wait is not None:
                    self.on_wait(f"the Dask scheduler has had no worker for {alone:.0f} s ({left} dense job(s) "
                                 f"left): waiting for one to come back, at most {self.give_up_s:.0f} s")
                    told = True
                pending = waiting()
                continue
            except StopIteration:
                pending = waiting()          # every future of this round yielded: the rest remain
                continue
            if fut.key in yielded:
                continue
            yielded.add(fut.key)
            yield fut.result()

    def close(self) -> None:
        if self._own:
            self.client.close()


def make_executor(scheduler: str | None = None, workers: int | None = None, on_wait=None) -> Executor:
    """None -> local process pool (serial with workers=1); an address -> Dask (on_wait: told when
    the scheduler has no worker)."""
    if scheduler:
        return DaskExecutor(scheduler, on_wait=on_wait)
    if workers == 1:
        return SerialExecutor()
    return LocalExecutor(workers)
