"""Run independent tasks in this process, on a local process pool, or on a Dask cluster.

Every backend calls the same module-level function with the same picklable arguments and
yields results as they complete (unordered), with a bounded number of tasks in flight so
results stream instead of piling up. Worker processes are started with "spawn": each
one creates its own OpenGL context (a context never survives a fork), and each dies with
the process that started it (even when that one is killed with SIGKILL).

    for result in map_unordered(fn, tasks, workers=2):
        ...

`scheduler` is a Dask scheduler address ("tcp://host:8786"); dask.distributed is imported
only then. Workers there must be able to import mvtex and read the same dataset path.
"""

from __future__ import annotations

import asyncio
import ctypes
import multiprocessing as mp
import numbers
import os
import re
import signal
import socket
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from mvtex.util.errors import OptionError

MAX_WORKERS = 64
"""Most local worker processes a run accepts. Each worker holds its own GL context and a
copy of the run's inputs (100-300 MB); a run also never starts more workers than the
cores it may use (`worker_count`)."""


SCHEDULER_TIMEOUT_S = 10.0
"""Seconds a Dask scheduler has to accept a connection and answer mvtex's handshake."""


def worker_count(workers: int) -> int:
    """The local worker processes a run starts for `workers` asked: at most the cores this
    process may use (`available_cores`); more would only take memory."""
    return max(1, min(int(workers), available_cores()))


def check_backend(workers: int | None = None, scheduler: str | None = None, *,
                  timeout: float | None = None) -> None:
    """Refuse (OptionError) a worker count outside 1..MAX_WORKERS, and a Dask scheduler
    address that is not `tcp://HOST:PORT` (or `HOST:PORT`), where nothing accepts a
    connection, or where what answers is not a Dask scheduler (no answer to Dask's
    handshake and identity request within `timeout` seconds): before any work starts or
    anything is written. `timeout` None: SCHEDULER_TIMEOUT_S."""

    if workers is not None and (isinstance(workers, (bool, np.bool_)) or not isinstance(workers, numbers.Integral)
                                or not 1 <= workers <= MAX_WORKERS):
        raise OptionError("workers", f"must be an integer in 1..{MAX_WORKERS}, got {workers!r}")
    if scheduler is None:
        return
    if not isinstance(scheduler, str):
        raise OptionError("scheduler", f"must be a Dask scheduler address tcp://HOST:PORT, got {type(scheduler).__name__}")
    match = re.fullmatch(r"(?:(?:tcp|tls)://)?(\[[0-9a-fA-F:]+\]|[A-Za-z0-9._-]+):(\d{1,5})/?", str(scheduler).strip())
    if not match or not 0 < int(match.group(2)) < 65536:
        raise OptionError("scheduler", f"must be a Dask scheduler address tcp://HOST:PORT, got {scheduler!r}")
    host, port = match.group(1).strip("[]"), int(match.group(2))
    timeout = SCHEDULER_TIMEOUT_S if timeout is None else float(timeout)
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as err:
        raise OptionError("scheduler", f"{host}:{port}: nothing accepts a connection there ({err.strerror or err}); "
                          "start one with `dask scheduler`") from None
    if not str(scheduler).strip().startswith("tls://"):  # TLS needs the user's certificates: connect only
        _check_dask_scheduler(f"tcp://{match.group(1)}:{port}", timeout)


def _check_dask_scheduler(address: str, timeout: float) -> None:
    """Refuse (OptionError) an address where no Dask scheduler answers Dask's handshake and an
    identity request within `timeout` seconds (a port that accepts and stays silent, an HTTP
    server, another protocol). Runs in a thread of its own: the caller may be inside an
    event loop (a notebook)."""

    try:
        from distributed.comm import connect  # noqa: PLC0415 (loaded on use)
    except ImportError as err:  # the original error, with the extra that provides it
        raise ImportError(f"{err}; a Dask scheduler needs `pip install mvtex[dist]`") from err

    async def identity():
        comm = await connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    def ask():
        return asyncio.run(asyncio.wait_for(identity(), timeout))

    with ThreadPoolExecutor(max_workers=1) as pool:
        try:
            reply = pool.submit(ask).result()
        except Exception as err:  # whatever answers there, it is not a scheduler: a timeout, garbage frames
            detail = f"no answer to Dask's handshake within {timeout:g} s" if isinstance(err, TimeoutError) \
                else f"its reply to Dask's handshake is not Dask's: {type(err).__name__}"
            raise OptionError("scheduler", f"{address} accepts connections but is not a Dask scheduler ({detail})") \
                from None
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        raise OptionError("scheduler", f"{address} is a Dask {reply.get('type') if isinstance(reply, dict) else '?'}, "
                          "not a scheduler")


def map_unordered(fn: Callable[..., Any], tasks: Sequence[tuple], *, workers: int = 1, scheduler: str | None = None,
                  max_in_flight: int | None = None) -> Iterator[Any]:
    """Yield fn(*task) for every task, in completion order.

    Args:
        fn: a module-level (picklable) function.
        tasks: argument tuples.
        workers: local processes (1 = run here, in this process, in order).
        scheduler: Dask scheduler address; takes precedence over `workers`.
        max_in_flight: tasks submitted ahead of the consumer (default 4 per worker).

    Exceptions raised by a task propagate to the caller (remaining tasks are cancelled).
    """
    tasks = list(tasks)
    if scheduler:
        yield from _dask(fn, tasks, scheduler, max_in_flight)
    elif worker_count(workers) <= 1:
        for task in tasks:
            yield fn(*task)
    else:
        workers = worker_count(workers)
        yield from _processes(fn, tasks, workers, max_in_flight or 4 * workers)


class ThreadState:
    """What a worker keeps between the tasks of one run (dataset, topology, GL context), one
    per thread: a Dask worker runs tasks in several threads at once (`dask worker` starts one
    per core by default), and a GL context is used by the thread that made it.

    `get(key, make)` returns this thread's value for run `key`, made by `make()` the first
    time; `set(key, value)` puts one in place (a value None drops it). A value replaced or
    dropped is released (`value.release()`).
    """

    def __init__(self) -> None:

        self._local = threading.local()

    def get(self, key: Any, make: Callable[[], Any]) -> Any:
        held = getattr(self._local, "held", None)
        if held is None or held[0] != key:
            self.set(None, None)  # the previous run's state goes before the next one is made
            held = self._local.held = (key, make())
        return held[1]

    def set(self, key: Any, value: Any) -> None:
        old = getattr(self._local, "held", None)
        self._local.held = None if value is None else (key, value)
        if old is not None and old[1] is not value:
            old[1].release()


@dataclass
class WorkerState:
    """What a worker thread keeps between the tasks of one run: its GL context (a
    `mvtex.render.context.GLContext`, released with the state when the worker made it) and,
    in subclasses, the run's opened inputs (`ThreadState` holds one per thread)."""

    ctx: Any
    owns_ctx: bool

    def release(self) -> None:
        if self.owns_ctx:
            self.ctx.release()


def _processes(fn, tasks: list, workers: int, max_in_flight: int) -> Iterator[Any]:

    parent_death_signal = threading.current_thread() is threading.main_thread()
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_die_with_parent,
                             initargs=(os.getpid(), parent_death_signal)) as pool:
        pending: set = set()
        it = iter(tasks)
        try:
            for task in it:
                pending.add(pool.submit(fn, *task))
                if len(pending) >= max_in_flight:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        yield fut.result()
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    yield fut.result()
        finally:
            for fut in pending:
                fut.cancel()


def _die_with_parent(parent_pid: int, parent_death_signal: bool) -> None:
    """Worker initializer: end this worker when the process that started it dies.

    A killed parent (SIGKILL, OOM killer) runs no cleanup, and its pool's workers would
    live on as orphans. On Linux the kernel sends SIGKILL on the parent's death
    (`prctl(PR_SET_PDEATHSIG)`; only when the pool was started from the parent's main
    thread, since the signal follows the *thread* that started the worker). Everywhere, a
    daemon thread also checks twice a second that the parent is still this process's
    parent and exits if not.
    """

    configure_threads(1)  # the workers fill the cores: one thread each, set before any library loads
    if parent_death_signal and sys.platform.startswith("linux"):

        PR_SET_PDEATHSIG = 1
        try:
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # died before the signal was armed
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="mvtex-parent-watch", daemon=True).start()


def _dask(fn, tasks: list, address: str, max_in_flight: int | None) -> Iterator[Any]:
    try:
        from dask.distributed import Client, as_completed  # noqa: PLC0415 (loaded on use)
    except ImportError as err:  # the original error, with the extra that provides it
        raise ImportError(f"{err}; a Dask scheduler needs `pip install mvtex[dist]`") from err

    # A bounded handshake (check_backend checked the address; this bounds a scheduler that
    # stops answering in between).
    with Client(address, timeout=SCHEDULER_TIMEOUT_S) as client:
        limit = max_in_flight or 4 * max(1, sum(client.nthreads().values()))
        it = iter(tasks)
        # range first: zip would take (and drop) one task more from `it` when range runs out
        pending = {client.submit(fn, *task, pure=False) for _, task in zip(range(limit), it)}
        queue = as_completed(list(pending))
        try:
            for fut in queue:
                result = fut.result()
                pending.discard(fut)
                fut.release()
                for task in _take(it, 1):
                    new = client.submit(fn, *task, pure=False)
                    pending.add(new)
                    queue.add(new)
                yield result
        finally:
            for fut in pending:
                fut.cancel()


def _take(it: Iterable, k: int) -> list:
    out = []
    for item in it:
        out.append(item)
        if len(out) == k:
            break
    return out


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity, else the machine's)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def configure_threads(threads: int | None = None) -> None:
    """Set the thread behaviour of the numeric libraries, deliberately and in one place: the
    command line calls it once at start (no count: each library uses the cores), every
    worker process with `threads=1` (the workers themselves fill the cores). A variable set
    by the user is kept.

    - OpenMP (torch, OpenBLAS) threads that wait sleep instead of spinning
      (OMP_WAIT_POLICY=PASSIVE): on a machine busy with other work, idle threads would
      otherwise take cores from it and from each other.
    - With `threads`: OMP_NUM_THREADS, OPENBLAS_NUM_THREADS, MKL_NUM_THREADS and torch's
      intra-op threads; with 1, llvmpipe rasterizes in the calling thread (LP_NUM_THREADS=0).

    Library variables are read when a library loads, so call it before the first heavy
    import; torch's count is also set if torch is loaded already.
    """

    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if threads is None:
        return
    n = max(1, int(threads))
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, str(n))
    if n == 1:
        os.environ.setdefault("LP_NUM_THREADS", "0")
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
