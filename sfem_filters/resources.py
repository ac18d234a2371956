"""What the machine lends a run: memory, cores, worker processes and BLAS threads.

Below every other layer (it imports nothing of the package's):

* the memory probe, :func:`available_memory`, which the smoother asks before it keeps its
  covariances (:func:`sfem_filters.filtering.smoother.check_memory`), the model before it caches
  modal stiffness derivatives and the rounds before they start fits side by side;
* the cores this process may use, :func:`usable_cores`, and the pool of worker processes the
  rounds' fits run in, :func:`process_pool`, whose workers leave Ctrl-C to their parent
  (:func:`starting_workers`);
* the BLAS threads of the filter's dense products, :func:`blas_threads`, under which the
  estimators' entry points run (:meth:`sfem_filters.filtering.iterated.IteratedSmoother.run`,
  :func:`sfem_filters.filtering.cyclic.cyclic_estimate`, the command line).

BLAS threads, measured by ``python benchmarks/blas_threads.py`` on a 2-core machine: the filter's
products are a few n x n matrix products, rank-m updates and Cholesky factors a frame, with n
from about 200 (the pinned benchmark) to about 5300 (the measured slice on a pixel lattice twice
as fine). At n ~ 200 a second BLAS thread made the quick start's snippet many times slower, on a
nearly idle machine as beside other jobs (thread hand-over costs more than a product of well
under a millisecond); at n ~ 1350 (the measured slice) two threads were slower beside other jobs,
a whole fit several times so; at n ~ 5300 beside other jobs the products took as long on two
threads as on one and the Cholesky factor longer. Runs are usually made beside other work
(the rounds' fits side by side in :func:`process_pool`, a batch, other users), so one thread is
the default (:data:`DEFAULT_BLAS_THREADS`); where the cores are known to be free for one large
run, the environment variable :data:`BLAS_THREADS_ENV` or an explicit ``blas_threads(n)`` around
the call gives it more.
"""
from __future__ import annotations

import contextlib
import functools
import multiprocessing
import os
import pickle
import resource
import signal
import threading
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import numpy as np
from threadpoolctl import threadpool_limits

__all__ = ["available_memory", "CGROUP_FILES", "usable_cores", "process_pool", "starting_workers", "blas_threads",
           "chosen_blas_threads",
           "limits_blas_threads", "DEFAULT_BLAS_THREADS", "BLAS_THREADS_ENV", "frame_threads", "chosen_frame_threads",
           "frame_map", "best_of"]


# --- memory ------------------------------------------------------------------------------------------------------

#: (limit, usage) files of the process's memory control group: cgroup v2, then v1.
CGROUP_FILES = (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"))


def _read_number(path: str) -> float | None:
    try:
        with open(path) as f:
            text = f.read().strip()
        return float(text) if text and text != "max" else None
    except (OSError, ValueError):
        return None


def available_memory() -> float | None:
    """Bytes available to new allocations, or None where the system does not say.

    The smaller of the machine's ``MemAvailable`` (Linux /proc/meminfo) and what the process's
    control group still allows (cgroup v2 ``memory.max - memory.current``, v1
    ``memory.limit_in_bytes - memory.usage_in_bytes``), as in a container or a batch slot, and what
    the process's address-space limit (``ulimit -v``) still allows. A Dask worker's own
    ``memory_limit`` is not seen here."""
    found = []
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    found.append(float(line.split()[1]) * 1024.0)
                    break
    except (OSError, ValueError, IndexError):
        pass
    for limit, used in CGROUP_FILES:
        cap, now = _read_number(limit), _read_number(used)
        if cap is not None and now is not None and cap < 2.0 ** 60:     # v1 writes a huge number for none
            found.append(max(cap - now, 0.0))
            break
    room = _address_space_room()
    if room is not None:
        found.append(room)
    return min(found) if found else None


def _address_space_room() -> float | None:
    """Bytes the process's address-space limit (``ulimit -v``, RLIMIT_AS) still allows, or None."""
    try:
        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/status") as f:
            size = next(float(line.split()[1]) * 1024.0 for line in f if line.startswith("VmSize:"))
    except (OSError, ValueError, StopIteration, AttributeError):
        return None
    return max(float(soft) - size, 0.0)


# --- cores and worker processes ----------------------------------------------------------------------------------

def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the system tells it, else all)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:                  # not on Linux
        return max(os.cpu_count() or 1, 1)


def _format_warnings_with(formatwarning=None) -> None:
    """A worker's initialiser: leave Ctrl-C (SIGINT) to the process that started it, which stops
    the pool (a terminal sends it to every process of the group, and a worker would otherwise
    print its own traceback); show warnings as that process does (``formatwarning``, if given)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if formatwarning is not None:
        warnings.formatwarning = formatwarning


def process_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of ``workers`` worker processes started afresh (``"spawn"``): no copy of this
    process's BLAS threads or locks. The workers format warnings as this process does at the call
    (``warnings.formatwarning``, for example the command line's one line, where it can be sent to
    them) and ignore Ctrl-C (SIGINT): the caller stops them (for example
    :meth:`sfem_filters.cardiac.closing._Fits.abort`: cancel, terminate, shut down; and
    :func:`starting_workers`). Raises ``OSError`` or ``ImportError`` where the system has no
    process semaphores (some sandboxes); the caller then runs the work itself."""
    try:
        pickle.dumps(warnings.formatwarning)
        initial = {"initializer": _format_warnings_with, "initargs": (warnings.formatwarning,)}
    except (pickle.PicklingError, AttributeError, TypeError):      # a local function: the workers keep Python's
        initial = {"initializer": _format_warnings_with}
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"), **initial)


@contextlib.contextmanager
def starting_workers():
    """Ctrl-C (SIGINT) ignored in this process while it starts worker processes (around the first
    ``submit`` to a :func:`process_pool`, which starts them), so that they begin with it ignored
    (a disposition that survives ``exec``) and a Ctrl-C sent to the whole terminal's process group
    does not stop a worker halfway through its start-up with a traceback; this process's own
    handler is back on leaving. Does nothing outside the main thread (where signals cannot be set)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, saved)


# --- BLAS threads ------------------------------------------------------------------------------------------------

#: BLAS threads of the estimators' entry points unless told otherwise: one (measured, the module
#: docstring and ``benchmarks/blas_threads.py``).
DEFAULT_BLAS_THREADS = 1

#: The environment variable that overrides :data:`DEFAULT_BLAS_THREADS`: a positive integer.
BLAS_THREADS_ENV = "SFEM_FILTERS_BLAS_THREADS"

_explicit: list = []                        # the explicit blas_threads(n) in force, innermost last


def _threads(name: str, value, text: bool = False) -> int:
    """``value`` (an int, or with ``text`` the text of one, as an environment variable holds it)
    as a positive number of threads, or a ValueError/TypeError naming ``name``."""
    expected = f"{name}: expected a positive integer number of BLAS threads, got {value!r}"
    if text:
        text = value.strip()
        if not text.isdigit() or int(text) < 1:
            raise ValueError(expected)
        return int(text)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(expected)
    if value < 1:
        raise ValueError(expected)
    return int(value)


def chosen_blas_threads(n=None) -> int:
    """The BLAS threads :func:`blas_threads` ``(n)`` sets: ``n`` where given; else those of the
    innermost explicit :func:`blas_threads` still in force; else the environment variable
    :data:`BLAS_THREADS_ENV`; else :data:`DEFAULT_BLAS_THREADS`.

    Raises
    ------
    ValueError, TypeError
        ``n`` or the environment variable is not a positive integer (the message names which).
    """
    if n is not None:
        return _threads("blas_threads(n)", n)
    if _explicit:
        return _explicit[-1].threads
    env = os.environ.get(BLAS_THREADS_ENV)
    if env is not None and env.strip():
        return _threads(f"environment variable {BLAS_THREADS_ENV}", env, text=True)
    return DEFAULT_BLAS_THREADS


class blas_threads:
    """Limit the BLAS libraries' threads (threadpoolctl) to :func:`chosen_blas_threads` ``(n)``.

    A context manager, or a setter: the limit applies from the call, and is lifted on leaving the
    ``with`` block or by :meth:`restore` (the threads in force before come back). An explicit
    ``n`` also holds for the entry points called inside (they take the innermost explicit choice
    instead of the default), so ``with blas_threads(2): IteratedSmoother().run(...)`` runs on two.

    Parameters
    ----------
    n : int, optional
        BLAS threads, >= 1; None: the enclosing explicit choice, else the environment variable
        :data:`BLAS_THREADS_ENV`, else :data:`DEFAULT_BLAS_THREADS`.

    Examples
    --------
    >>> from threadpoolctl import threadpool_info
    >>> with blas_threads(1):
    ...     all(p["num_threads"] == 1 for p in threadpool_info() if p["user_api"] == "blas")
    True
    """

    def __init__(self, n=None):
        self.threads = chosen_blas_threads(n)
        self._explicit = n is not None
        self._limits = threadpool_limits(limits=self.threads, user_api="blas")
        if self._explicit:
            _explicit.append(self)
        self._active = True

    def restore(self) -> None:
        """Give the BLAS libraries back the threads they had before (once; later calls do nothing)."""
        if not self._active:
            return
        self._active = False
        if self in _explicit:
            _explicit.remove(self)
        self._limits.restore_original_limits()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.restore()

    def __repr__(self) -> str:
        return f"blas_threads({self.threads})"


def limits_blas_threads(run):
    """Decorate an estimator's entry point to run under :func:`blas_threads` ``()`` (the default,
    the environment variable or the enclosing explicit choice). Another number of threads may
    change the last bits of the results (the order of floating-point sums), not more."""
    @functools.wraps(run)
    def limited(*args, **kwargs):
        with blas_threads():
            return run(*args, **kwargs)
    return limited


# --- threads over a fit's frames ----------------------------------------------------------------------------------

_frame_local = threading.local()            # per thread: the frame_threads(n) in force there, innermost last


def _frame_stack() -> list:
    stack = getattr(_frame_local, "stack", None)
    if stack is None:
        stack = _frame_local.stack = []
    return stack


def chosen_frame_threads() -> int:
    """The threads :func:`frame_map` uses: those of the innermost :class:`frame_threads` in force in
    this thread, else 1 (so the pool's own threads map one frame at a time, never nesting)."""
    stack = _frame_stack()
    return stack[-1] if stack else 1


class frame_threads:
    """Take a fit's independent per-frame work on ``n`` threads (a context manager; default 1 outside).

    Each frame's sensitivity of a linearisation (Eq. 33, :meth:`sfem_filters.model.SFEMModel.linearise`)
    depends on that frame's state alone, so the frames can be taken side by side: every thread
    writes its own frames' rows with the same operations, so the results are the same to the bit
    whatever ``n`` (each thread's BLAS calls stay on the BLAS threads set by :class:`blas_threads`).
    Their products and loops release the interpreter's lock, so a second thread uses a second core
    for that part of a fit; the rest, its forward and backward passes, runs frame after frame, so
    the fit as a whole gains less (``benchmarks/frame_threads.py`` prints the ratio on the measured
    slice's baseline fit, against one thread in the same run). Use it where
    the cores would otherwise idle: the rounds' fits made in their own process while the worker
    processes wait
    (:func:`~sfem_filters.cardiac.closing.closing_the_loop`), not inside workers already busy.

    Parameters
    ----------
    n : int
        Threads, >= 1.

    Examples
    --------
    >>> with frame_threads(2):
    ...     frame_map(lambda t: t * t, range(4)), chosen_frame_threads()
    ([0, 1, 4, 9], 2)
    >>> chosen_frame_threads()
    1
    """

    def __init__(self, n):
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)):
            raise TypeError(f"n: expected a positive integer number of threads, got {n!r}")
        if n < 1:
            raise ValueError(f"n: expected a positive integer number of threads, got {n!r}")
        self.threads = int(n)

    def __enter__(self):
        _frame_stack().append(self.threads)
        return self

    def __exit__(self, *exc) -> None:
        _frame_stack().pop()

    def __repr__(self) -> str:
        return f"frame_threads({self.threads})"


def frame_map(fn, items) -> list:
    """``[fn(i) for i in items]``, on :func:`chosen_frame_threads` threads (in order; an error of
    ``fn`` is raised as it is). The first item is taken alone before the others start, so that any
    cache it fills (a system's divided differences, say) is filled once, not by every thread."""
    items = list(items)
    n = min(chosen_frame_threads(), len(items) - 1)
    if n <= 1:
        return [fn(i) for i in items]
    first = fn(items[0])
    with ThreadPoolExecutor(n) as pool:
        return [first] + list(pool.map(fn, items[1:]))


def best_of(fn, repeat: int) -> float:
    """Least wall time (s) of ``repeat`` calls of ``fn()``: the benchmarks' timer (the least is the
    run least disturbed by whatever else the machine does).

    >>> best_of(lambda: None, 3) >= 0.0
    True
    """
    if int(repeat) < 1:
        raise ValueError(f"repeat: expected an integer >= 1, got {repeat!r}")
    best = np.inf
    for _ in range(int(repeat)):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best
