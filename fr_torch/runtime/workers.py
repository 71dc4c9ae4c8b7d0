"""How worker processes start and end (imports no torch, so a command can start them before it loads it).

Workers are started with ``forkserver`` where available (else ``spawn``): no OpenMP state or lock
of the parent is inherited.  The fork server imports the library once (:data:`PRELOAD`) and every
worker is forked from it, already loaded, so a pool starts in milliseconds instead of each worker
importing torch (about a second and a half of CPU each).  :func:`start_worker_server` starts that
server ahead of time, e.g. while the command-line process is still importing torch itself.

Every pool of the library is a :class:`WorkerPool`.  Its workers end with the process that
started them, however that one ends (an exception, SIGTERM, SIGKILL, the out-of-memory killer): each watches
its parent (:func:`exit_with_parent`) and exits within milliseconds of its death.  A worker would
otherwise wait for work forever -- it holds both ends of its own task queue, so it never sees the
queue close -- and, because every worker holds the fork server's "clients alive" pipe and the
resource tracker's pipe, so would the fork server and the resource tracker.  Once the workers are
gone, both of those end by themselves (each exits when the last holder of its pipe is gone).
Workers ignore SIGINT: a terminal's CTRL-C reaches the whole process group, and the parent
decides what to stop (:func:`fr_torch.runtime.pipeline.ordered_pool_map` kills the workers whose
results it will no longer read).

A command turns SIGTERM, and CTRL-C's SIGINT, into one exception (:class:`Stopped`, a
KeyboardInterrupt; :func:`interrupt_on_signals`), so that a service manager's, scheduler's or
container's stop runs the same clean-up as CTRL-C: finished output is kept, the pool is shut down,
the exit status is 128 + the signal's number (:func:`interrupt_exit_status`).  A stop that
arrives while a pool is starting a worker is raised once the worker is started
(:func:`stops_held`), so that the pool knows every worker it has to stop.
"""
from __future__ import annotations

import contextlib
import gc
import math
import multiprocessing
import multiprocessing.forkserver
import os
import signal
import threading
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Callable, Iterator, Sequence

#: Modules the fork server imports once for all workers (``__main__`` as multiprocessing does).
#: Not ``torch._dynamo`` (1-2 s): the refinement no longer builds a ``torch.optim.Adam`` object,
#: whose constructor imported it (it calls torch.optim's functional Adam: fr_torch.core.search.passes._FusedAdam).
PRELOAD = ["__main__", "fr_torch.runtime.pipeline", "fr_torch.runtime.estimator"]


def context() -> multiprocessing.context.BaseContext:
    """The multiprocessing context of every worker pool (forkserver, preloading :data:`PRELOAD`)."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(PRELOAD)  # no effect once the server runs
        return ctx
    return multiprocessing.get_context("spawn")


def start_worker_server() -> None:
    """Start the fork server now (it loads the library in its own process, in parallel with the
    caller); a no-op where workers are spawned or the server already runs."""
    if context().get_start_method() == "forkserver":
        multiprocessing.forkserver.ensure_running()


class WorkerPool(ProcessPoolExecutor):
    """A :class:`~concurrent.futures.ProcessPoolExecutor` of ``workers`` processes (:func:`context`)
    that run ``initializer(*initargs)`` once each, ignore SIGINT and exit when this process dies
    (:func:`exit_with_parent`); :meth:`submit` holds a stop (:func:`stops_held`) while it may be
    starting a worker."""

    def __init__(self, workers: int, initializer: Callable | None = None, initargs: Sequence = ()):
        super().__init__(workers, mp_context=context(), initializer=_start_worker,
                         initargs=(initializer, tuple(initargs)))

    def submit(self, fn, /, *args, **kwargs):
        """``ProcessPoolExecutor.submit``; a stop that arrives meanwhile is raised once it returns.
        (A stop raised while a worker is being started would leave that worker unknown to the pool:
        it would start after this process has gone and fail there with a traceback.)"""
        with stops_held():
            return super().submit(fn, *args, **kwargs)


def _start_worker(initializer: Callable | None, initargs: tuple) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides (a terminal's CTRL-C reaches the group)
    exit_with_parent()
    if initializer is not None:
        initializer(*initargs)


#: Exit status of a worker that ended because its parent died.
ORPHAN_EXIT_STATUS = 1


def settle_heap() -> None:
    """Put every object alive now (the imports, the models, the estimator) out of the garbage
    collector's reach (:func:`gc.freeze`), in a process fR owns (a command, a worker) once it is
    set up.  The collector's first full pass over torch's many objects (about 40 ms on a 2-core
    machine) would otherwise land in the first search; later passes see only newer objects."""
    gc.freeze()


def exit_with_parent() -> None:
    """In a process started by :mod:`multiprocessing` (any start method): end it (``os._exit``, no
    clean-up) as soon as its parent process is gone; a no-op in a process that has no such parent.

    A daemon thread waits on the parent's sentinel, a pipe whose write end only the parent holds
    (for ``forkserver`` the parent is the process that asked for the worker, not the fork
    server), so it wakes when the parent exits or is killed, SIGKILL included.  The parent closes
    it otherwise only after the worker has ended (when its ``Process`` object is collected)."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return
    threading.Thread(target=_exit_when_gone, args=(parent,), name="fr-exit-with-parent", daemon=True).start()


def _exit_when_gone(parent) -> None:
    parent.join()  # returns when the parent's sentinel pipe reaches end-of-file
    os._exit(ORPHAN_EXIT_STATUS)


class Stopped(KeyboardInterrupt):
    """A stop signal (SIGTERM, or SIGINT under :func:`interrupt_on_signals`) received by the main
    thread, raised where that thread was, as CTRL-C raises :class:`KeyboardInterrupt` (a subclass,
    so every clean-up written for CTRL-C runs).  ``signum``: the signal's number."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


#: Stops held by :func:`stops_held` (main thread only): the depth of nested blocks and the first
#: signal held.
_HELD: dict = {"depth": 0, "signum": None}


def _raise_stopped(signum, frame) -> None:
    if _HELD["depth"]:
        _HELD["signum"] = _HELD["signum"] or signum
        return
    raise Stopped(signum)


@contextlib.contextmanager
def stops_held() -> Iterator[None]:
    """In the main thread, a stop that :func:`interrupt_on_signals` would raise during the block is
    raised when the block ends instead (for steps that must not be cut in the middle); elsewhere,
    or without those handlers, a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _HELD["depth"] += 1
    try:
        yield
    finally:
        _HELD["depth"] -= 1
        if not _HELD["depth"] and _HELD["signum"] is not None:
            signum, _HELD["signum"] = _HELD["signum"], None
            raise Stopped(signum)


#: Signals a command turns into :class:`Stopped` (:func:`interrupt_on_signals`).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def interrupt_on_signals(signums: Sequence[int] = STOP_SIGNALS) -> Iterator[None]:
    """While the block runs, each of ``signums`` raises :class:`Stopped` in the main thread, as
    SIGINT raises KeyboardInterrupt (held meanwhile by :func:`stops_held`); the previous handlers
    come back afterwards.  A signal whose handler is neither the default nor Python's SIGINT
    handler (ignored, as ``nohup`` does for SIGHUP or a shell for a background job's SIGINT, or
    the caller's own) is left alone.  A no-op outside the main thread (Python delivers signals to
    it only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    defaults = (signal.SIG_DFL, signal.default_int_handler)
    previous = {signum: signal.signal(signum, _raise_stopped) for signum in signums
                if signal.getsignal(signum) in defaults}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


@contextlib.contextmanager
def keep_signal_handler(signum: int = signal.SIGTERM) -> Iterator[None]:
    """After the block, ``signum``'s handler is what it was before when that was a Python function
    (e.g. :func:`interrupt_on_signals`'s), whatever the block installed: for a library that sets
    its own on start (``ray.init`` makes SIGTERM ``sys.exit``, which would skip the command's
    one-line report and exit status)."""
    handler = signal.getsignal(signum) if threading.current_thread() is threading.main_thread() else None
    try:
        yield
    finally:
        if callable(handler):
            signal.signal(signum, handler)


def interrupt_exit_status(interrupt: KeyboardInterrupt) -> int:
    """A command's exit status after ``interrupt``: 128 + the signal's number (130 for CTRL-C's
    SIGINT, 143 for SIGTERM), as a shell reports a process killed by that signal."""
    return 128 + getattr(interrupt, "signum", signal.SIGINT)


def cgroup_cpu_limit(root: str | Path = "/sys/fs/cgroup") -> float | None:
    """CPUs granted by the cgroup CPU quota (a container's ``--cpus``), or None where there is no
    quota or no cgroup file (cgroup v2 ``cpu.max``, else v1 ``cpu/cpu.cfs_quota_us`` / ``_period_us``)."""
    root = Path(root)
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return quota / period if quota > 0 and period > 0 else None


def usable_cores() -> int:
    """CPU cores this process may use: its affinity mask (else all cores), capped by the cgroup CPU
    quota (in a container with ``--cpus 2`` on a 64-core host that is 2, not 64)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    limit = cgroup_cpu_limit()
    return max(1, min(cores, math.ceil(limit))) if limit else cores
