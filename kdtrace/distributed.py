"""Units of work on a Dask cluster: a local one by default, an existing one on request.

How to use::

    from kdtrace.distributed import Unit, run_units
    results = run_units([Unit("case-1", (1,)), Unit("case-2", (2,))], square)   # embedded LocalCluster
    results = run_units(units, square, scheduler="tcp://head:8786")             # an existing scheduler
    [(r.key, r.value, r.worker, r.seconds) for r in results]

A *unit* is one call ``fn(*unit.args)`` (``fn(shared, *unit.args)`` when ``shared`` is
given: it is sent to every worker once, not once per unit). Units should be
idempotent: write their result atomically under a content-hashed name and return early
when it is already there, so a rerun, a retried unit or a second client costs nothing.
The Dask key of a unit is its ``key``, so two clients of one scheduler submitting the
same unit share one task.

Where the work runs (:func:`connect`):

* ``scheduler`` argument, else ``$KDTRACE_SCHEDULER``, else ``[distributed] scheduler``:
  the address of a running ``dask scheduler``. An unreachable address raises
  :class:`SchedulerUnreachableError` after ``connect_timeout`` seconds.
* otherwise (or ``"local"``): an embedded ``LocalCluster`` of worker *processes* (numba's
  thread pool is not safe to enter from two threads of one process), ``workers`` of them
  (0: ``cores // threads_per_worker``), each running one unit at a time with
  ``threads_per_worker`` numba, PyTorch and Dr.Jit threads, so workers x threads = cores.

Every worker is checked against this process's versions of Python and of the packages
stamped on every result (:data:`VERSIONED_PACKAGES`: kdtrace, numpy, numba, mitsuba,
drjit, torch, embreex, ...): a mismatch raises
:class:`VersionMismatchError` naming worker, package and both versions, when connecting
and again inside every unit (a worker may join later).

Faults: a unit whose worker dies is rescheduled by Dask on another worker (the nanny
restarts the dead one); a unit that raises is retried ``retries`` times and then
reported as :class:`UnitError` with the unit's key, after the remaining units are
cancelled. Progress is a tqdm bar advanced as units complete, and the dashboard link
is printed when there is one.
"""

from __future__ import annotations

import contextlib
import functools
import os
import platform
import socket
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from kdtrace import provenance
from kdtrace.config import DEFAULT_CONFIG, DistributedConfig

#: Environment variable naming the scheduler to connect to.
SCHEDULER_ENV = "KDTRACE_SCHEDULER"
#: Environment variable telling a worker of our embedded cluster its compute threads.
THREADS_ENV = "KDTRACE_WORKER_THREADS"
#: Packages whose versions must match between the client and every worker: those stamped on every result.
VERSIONED_PACKAGES = provenance.PACKAGES
#: ``scheduler`` value that asks for the embedded LocalCluster.
LOCAL = "local"


class SchedulerUnreachableError(ConnectionError):
    """No Dask scheduler answered at the given address."""


class VersionMismatchError(RuntimeError):
    """A worker runs other versions of the packages results depend on."""


class UnitError(RuntimeError):
    """A unit of work failed (after its retries); the message names the unit."""


@dataclass(frozen=True)
class Unit:
    """One unit of work.

    Attributes
    ----------
    key : str
        Unique, stable name (the Dask key): a content hash or a name derived from one.
    args : tuple
        Positional arguments of the unit's function (picklable).
    """

    key: str
    args: tuple = ()


@dataclass(frozen=True)
class UnitResult:
    """What one unit returned, where and how long it ran.

    Attributes
    ----------
    key : str
        The unit's key.
    value : Any
        The function's return value.
    worker : str
        Dask worker address, or ``host:pid`` outside Dask.
    seconds : float
        Wall time of the call on the worker, seconds (versions check excluded).
    """

    key: str
    value: Any
    worker: str
    seconds: float


# ------------------------------------------------------------------ worker side
@functools.cache
def package_versions() -> dict[str, str]:
    """Python and :data:`VERSIONED_PACKAGES` versions of this process ("absent" when missing)."""
    return {"python": platform.python_version(), **provenance.package_versions()}


def _worker_versions() -> dict[str, str]:
    """:func:`package_versions` of the worker it runs on (pickled by reference, never by value)."""
    return package_versions()


def version_differences(expected: dict[str, str], actual: dict[str, str]) -> list[str]:
    """``"package: client X, worker Y"`` for every package whose versions differ."""
    return [f"{name}: client {expected[name]}, worker {actual.get(name, 'absent')}"
            for name in sorted(expected) if actual.get(name, "absent") != expected[name]]


def worker_identity() -> str:
    """The Dask worker address when called inside a task, else ``host:pid``."""
    if "distributed" in sys.modules:
        from distributed import get_worker

        with contextlib.suppress(ValueError):
            return get_worker().address
    return f"{socket.gethostname()}:{os.getpid()}"


def worker_threads() -> int:
    """Compute threads a unit may use here.

    Our embedded cluster says it in ``$KDTRACE_WORKER_THREADS``; on another worker, the
    cores divided by the worker's task threads (one ``dask worker`` process per machine
    is assumed); outside Dask, numba's current count.
    """
    if os.environ.get(THREADS_ENV):
        return max(1, int(os.environ[THREADS_ENV]))
    if "distributed" in sys.modules:
        from distributed import get_worker

        with contextlib.suppress(ValueError):
            return max(1, (os.cpu_count() or 1) // get_worker().state.nthreads)
    import numba

    return numba.get_num_threads()


def limit_threads(threads: int) -> None:
    """Use ``threads`` compute threads: numba (in the calling thread), and PyTorch / Dr.Jit when loaded.

    numba's setting is per calling thread and capped by its pool (``NUMBA_NUM_THREADS``,
    by default the cores); idle pool threads cost nothing.
    """
    import numba

    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)
    if "drjit" in sys.modules:
        sys.modules["drjit"].set_thread_count(threads)


def _execute(fn: Callable, args: tuple, expected: dict[str, str]) -> tuple[Any, str, float]:
    """Run one unit on a worker: check versions, limit threads, call, time."""
    worker = worker_identity()
    differences = version_differences(expected, package_versions())
    if differences:
        raise VersionMismatchError(f"worker {worker} refused: " + "; ".join(differences))
    threads = worker_threads()
    limit_threads(threads)
    started = time.perf_counter()
    value = fn(*args)
    seconds = time.perf_counter() - started
    limit_threads(threads)  # Dr.Jit's pool exists only once a unit imported it
    return value, worker, seconds


# ------------------------------------------------------------------ client side
def scheduler_address(scheduler: str | None = None, config: DistributedConfig | None = None) -> str | None:
    """The scheduler to use: the argument, ``$KDTRACE_SCHEDULER``, the configuration; None: local."""
    config = config or DEFAULT_CONFIG.distributed
    address = scheduler or os.environ.get(SCHEDULER_ENV) or config.scheduler
    return None if not address or address == LOCAL else address


def local_cluster_size(workers: int | None = None, config: DistributedConfig | None = None) -> tuple[int, int]:
    """(worker processes, compute threads per worker) of the embedded cluster.

    Parameters
    ----------
    workers : int, optional
        Worker processes (default ``[distributed] workers``; 0: ``cores // threads_per_worker``).
    config : DistributedConfig, optional

    Returns
    -------
    (int, int)
        With ``workers`` given, threads are ``max(1, cores // workers)``.
    """
    config = config or DEFAULT_CONFIG.distributed
    cores = os.cpu_count() or 1
    workers = config.workers if workers is None else workers
    if workers < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    if workers == 0:
        threads = min(config.threads_per_worker, cores)
        return max(1, cores // threads), threads
    return workers, max(1, cores // workers)


def check_worker_versions(client: Any) -> None:
    """Refuse the cluster when a worker's package versions differ from this process's.

    Raises
    ------
    VersionMismatchError
        Naming each mismatching worker, package and both versions.
    """
    expected = package_versions()
    problems = [f"worker {address}: " + "; ".join(differences)
                for address, versions in sorted(client.run(_worker_versions).items())
                if (differences := version_differences(expected, versions))]
    if problems:
        raise VersionMismatchError("workers with other package versions than this client are refused (install "
                                   "the same versions everywhere):\n  " + "\n  ".join(problems))


def _connect_existing(address: str, config: DistributedConfig) -> Any:
    from distributed import Client

    try:
        return Client(address, timeout=config.connect_timeout, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as error:
        raise SchedulerUnreachableError(
            f"no Dask scheduler answered at {address!r} within {config.connect_timeout:g} s ({error}). Start one "
            f"with `dask scheduler` and workers with `dask worker {address}`, or unset --scheduler / "
            f"${SCHEDULER_ENV} to use a local cluster") from None


def _start_local(workers: int | None, config: DistributedConfig) -> tuple[Any, Any]:
    from distributed import Client, LocalCluster

    count, threads = local_cluster_size(workers, config)
    # Not NUMBA_NUM_THREADS: a worker process may import numba (through the client's main
    # module) before the nanny's environment is applied, and numba refuses a later change.
    # Each unit calls limit_threads instead; Dask's nanny already sets OMP_NUM_THREADS=1.
    cluster = LocalCluster(n_workers=count, threads_per_worker=1, processes=True,
                           dashboard_address=config.dashboard_address or None, env={THREADS_ENV: str(threads)})
    try:
        return cluster, Client(cluster, set_as_default=False)
    except BaseException:
        cluster.close()
        raise


@contextlib.contextmanager
def connect(scheduler: str | None = None, workers: int | None = None, config: DistributedConfig | None = None,
            announce: bool = True) -> Iterator[Any]:
    """A ``distributed.Client`` on an existing scheduler or on an embedded LocalCluster.

    Parameters
    ----------
    scheduler : str, optional
        Scheduler address; None: ``$KDTRACE_SCHEDULER`` or the configuration; ``"local"``
        or nothing found: start a LocalCluster (closed on exit).
    workers : int, optional
        Worker processes of the LocalCluster (see :func:`local_cluster_size`).
    config : DistributedConfig, optional
        Default ``[distributed]``.
    announce : bool
        Print the scheduler and dashboard link to stderr.

    Raises
    ------
    SchedulerUnreachableError
        Nothing answers at the address within ``connect_timeout`` seconds.
    VersionMismatchError
        A worker has other package versions (see :func:`check_worker_versions`).
    """
    config = config or DEFAULT_CONFIG.distributed
    address = scheduler_address(scheduler, config)
    cluster = None
    if address is None:
        cluster, client = _start_local(workers, config)
    else:
        client = _connect_existing(address, config)
    try:
        check_worker_versions(client)
        if announce:
            where = f"local cluster of {len(client.scheduler_info()['workers'])} workers" if cluster else address
            link = f", dashboard {client.dashboard_link}" if client.dashboard_link else ""
            print(f"dask: {where}{link}", file=sys.stderr)
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run_units(units: Sequence[Unit], fn: Callable, scheduler: str | None = None, *, client: Any = None,
              shared: Any = None, workers: int | None = None, progress: bool | None = None,
              description: str = "units", config: DistributedConfig | None = None) -> list[UnitResult]:
    """Run ``fn`` over ``units`` on a Dask cluster; results in the order of ``units``.

    Parameters
    ----------
    units : sequence of Unit
        Keys must be unique.
    fn : callable
        Module-level (picklable) function, called as ``fn(*unit.args)`` or, with
        ``shared``, ``fn(shared, *unit.args)``.
    scheduler : str, optional
        As in :func:`connect`; ignored when ``client`` is given.
    client : distributed.Client, optional
        An open client to use (its cluster is left running).
    shared : object, optional
        Sent to the workers once (``Client.scatter``) and passed first to every call.
    workers : int, optional
        Worker processes of an embedded LocalCluster.
    progress : bool, optional
        tqdm bar fed by completed units (None: only on a terminal).
    description : str
        Label of the bar.
    config : DistributedConfig, optional
        Default ``[distributed]``: timeouts, retries, dashboard, cluster size.

    Returns
    -------
    list of UnitResult

    Raises
    ------
    UnitError
        A unit raised (after ``retries`` further attempts) or its workers kept dying;
        the other units are cancelled.
    SchedulerUnreachableError, VersionMismatchError
        See :func:`connect`.
    """
    keys = [unit.key for unit in units]
    if len(set(keys)) != len(keys):
        raise ValueError("unit keys must be unique")
    if not units:
        return []
    config = config or DEFAULT_CONFIG.distributed
    if client is None:
        with connect(scheduler, workers, config, announce=progress is not False) as own:
            return run_units(units, fn, client=own, shared=shared, progress=progress, description=description,
                             config=config)
    from distributed import as_completed
    from tqdm import tqdm

    expected = package_versions()
    prefix = () if shared is None else (client.scatter(shared, broadcast=True),)
    futures = {client.submit(_execute, fn, (*prefix, *unit.args), expected, key=unit.key, pure=False,
                             retries=config.retries): unit.key for unit in units}
    results: dict[str, UnitResult] = {}
    with tqdm(total=len(units), desc=description, unit="unit", disable=None if progress is None else not progress) as bar:
        for future in as_completed(futures, loop=client.loop):
            key = futures[future]
            try:
                value, worker, seconds = future.result()
            except Exception as error:
                client.cancel(list(futures))
                raise UnitError(f"unit {key} failed: {type(error).__name__}: {error}") from error
            results[key] = UnitResult(key, value, worker, seconds)
            bar.update()
    return [results[key] for key in keys]
