"""Run one function over chunks of work: in this process, on local worker processes, or on a Ray
cluster — the small abstraction the per-frame stages share.

    for result in run_chunks(fn, chunks, executor="local", workers=2):
        ...                      # results arrive as chunks finish (completion order, not input order)

- ``workers=1`` (or a single chunk): plain calls in this process, no pool.
- ``executor="local"``: a ``concurrent.futures.ProcessPoolExecutor`` started with the
  ``forkserver`` method (see :data:`START_METHOD`). ``fn`` is sent to each worker once, when it
  starts; the chunks travel alone.
- ``executor="ray"``: ``ray.init(address=ray_address)`` (None starts a local Ray instance) and one
  Ray task per chunk; ``fn`` is put into the object store once. The folders ``fn`` reads and
  writes must have the same path on every node (a shared file system).

``fn`` must be picklable (a module-level function, or an instance of a module-level class whose
module every worker can import). What a worker should build only once (a ray caster, an opened
session) goes through :func:`process_cache`: one build per process, whichever executor runs it.

A caller that does not name an executor (``executor=None``) gets the one of the innermost
:func:`executor_scope` (``"local"`` outside any): how one ``annotate --executor ray`` sends every
stage's chunks (registration's arm positions as well as the label chunks) to the same cluster
without each stage's room knowing of it. Inside a scope, a Ray instance is started (or joined)
once, by the first Ray run, and shut down when the scope ends; inside a Ray task
(``ray.is_initialized()``) the runs join the task's own cluster, so a task may run its own chunks
as further tasks (Ray lends a task's CPU to the others while it waits for them).
"""

from __future__ import annotations

import contextvars
import multiprocessing
import os
import pickle
import signal
import socket
from collections import OrderedDict
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

from tdof20.errors import TdofError
from tdof20.progress import progress as _progress

EXECUTORS = ("local", "ray")
# fork would copy a parent that may already run open3d's / OpenMP's thread pools (a child can
# then hang on a lock held by a thread that was not copied); spawn re-imports everything in every
# worker. forkserver forks the workers from a clean server process that imported this package's
# heavy modules once (see _PRELOAD). Measured in benchmarks/label_speed.py --start-methods.
START_METHOD = "forkserver"
_PRELOAD = ["tdof20.annotate.label"]


# ---------------------------------------------------------------------------------------------
# the executor of a scope
# ---------------------------------------------------------------------------------------------
@dataclass
class _Scope:
    executor: str
    ray_address: str | None
    workers: int | None       # a local Ray instance's CPUs (None: every core)
    started_ray: bool = False  # this scope started (or joined) Ray: it shuts it down at its end


_SCOPE: "contextvars.ContextVar[_Scope | None]" = contextvars.ContextVar("tdof20_executor_scope", default=None)


@contextmanager
def executor_scope(executor: str = "local", ray_address: str | None = None,
                   workers: int | None = None, start: bool = False) -> Iterator[None]:
    """Within the block, :func:`run_chunks` calls that name no executor use ``executor`` (and
    ``ray_address``); the first Ray run starts a local instance of ``workers`` CPUs (None = every
    core) or joins ``ray_address``, and it stays up until the block ends (one start for all the
    stages of a run). ``start``: start (or join) Ray on entering already, so that a cluster that
    cannot be reached is a TdofError before the block runs. Scopes nest; the innermost counts."""
    if executor not in EXECUTORS:
        raise TdofError(f"executor must be one of {', '.join(EXECUTORS)}, got {executor!r}")
    scope = _Scope(executor, ray_address, None if workers is None else resolve_workers(workers))
    if start and executor == "ray":
        scope.started_ray = ray_init(ray_address, scope.workers)
    token = _SCOPE.set(scope)
    try:
        yield
    finally:
        _SCOPE.reset(token)
        if scope.started_ray:
            import ray

            ray.shutdown()


def current_executor() -> tuple[str, str | None]:
    """(executor, ray_address) of the innermost :func:`executor_scope`; ("local", None) outside."""
    scope = _SCOPE.get()
    return ("local", None) if scope is None else (scope.executor, scope.ray_address)


# ---------------------------------------------------------------------------------------------
# per-process cache
# ---------------------------------------------------------------------------------------------
_CACHE: "OrderedDict[Any, Any]" = OrderedDict()
_CACHE_SIZE = 2


def process_cache(key: Any, build: Callable[[], Any]) -> Any:
    """``build()`` once per process and ``key`` (the last two keys kept): how a worker keeps its
    ray caster and opened session across the chunks it runs, under any executor."""
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    value = build()
    _CACHE[key] = value
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return value


# ---------------------------------------------------------------------------------------------
# local worker processes
# ---------------------------------------------------------------------------------------------
_WORKER_FN: Callable | None = None


def _init_worker(fn: Callable) -> None:
    global _WORKER_FN
    _WORKER_FN = fn
    # Ctrl-C reaches the whole process group: the parent alone handles it (it cancels the queued
    # chunks and lets the running ones finish), so a worker never dies half-way through a file
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # one open3d thread a worker: the pool already has a worker a core (OMP_NUM_THREADS does not
    # reach open3d's own thread pool)
    from tdof20.o3d import o3d

    o3d.utility.set_max_threads(1)


def _call_worker(chunk: Any) -> Any:
    return _WORKER_FN(chunk)


def _context(start_method: str | None):
    method = start_method or START_METHOD
    if method not in multiprocessing.get_all_start_methods():
        method = "spawn"
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload(_PRELOAD)
    return ctx


def _run_local(fn: Callable, chunks: list, workers: int, start_method: str | None, advance) -> Iterator:
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=_context(start_method),
                               initializer=_init_worker, initargs=(fn,))
    # the workers already share the cores: one OpenMP thread each (open3d's ICP, normals, TSDF), or
    # every worker runs a thread per core and they fight (measured: registration of a 3,200-frame
    # scene 266 s -> 224 s on 2 cores). A user's OMP_NUM_THREADS is kept. The worker processes
    # (and the forkserver, started with the first of them) inherit the environment of that moment.
    omp = os.environ.get("OMP_NUM_THREADS")
    if omp is None:
        os.environ["OMP_NUM_THREADS"] = "1"
    try:
        # at most 2 chunks per worker queued: an interrupted run has little in flight
        todo = iter(enumerate(chunks))
        running = {}
        for i, c in todo:
            running[pool.submit(_call_worker, c)] = i
            if len(running) >= 2 * workers:
                break
        if omp is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        while running:
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in done:
                i = running.pop(f)
                try:
                    result = f.result()
                except BrokenProcessPool:
                    raise TdofError("a local worker process died (killed, out of memory, or the calling script "
                                    "lacks `if __name__ == '__main__':`); rerun to resume, or use workers=1") from None
                nxt = next(todo, None)
                if nxt is not None:
                    running[pool.submit(_call_worker, nxt[1])] = nxt[0]
                advance(chunks[i])
                yield result
    finally:
        if omp is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        pool.shutdown(wait=True, cancel_futures=True)


# ---------------------------------------------------------------------------------------------
# Ray
# ---------------------------------------------------------------------------------------------
def _ray_task(fn: Callable, chunk: Any) -> bytes:
    # pickled here, unpickled by the caller: Ray hands numpy arrays out of its object store
    # read-only (zero copy), and a caller that fills or edits a result in place (open3d's
    # Vector3dVector, for one) must get the same writable arrays as from the other executors
    return pickle.dumps(fn(chunk), protocol=pickle.HIGHEST_PROTOCOL)


def _probe(address: str, timeout: float = 5.0) -> None:
    """Fail fast (a TdofError) when nothing listens at a 'host:port' address; ray.init itself
    retries for a long while before it gives up."""
    addr = address.split("://", 1)[-1]
    host, sep, port = addr.rpartition(":")
    if not sep and addr.strip() in ("auto", "local"):
        return  # let Ray resolve it
    if not sep or not port.isdigit() or not host.strip("[] "):
        # Ray would log its own traceback ("Failed to convert ... to host:port") before failing
        raise TdofError(f"--ray-address {address!r} is not HOST:PORT (e.g. 10.0.0.5:6379), 'auto' or "
                        f"ray://HOST:PORT")
    try:
        socket.create_connection((host.strip("[]") or "127.0.0.1", int(port)), timeout=timeout).close()
    except OSError as e:
        raise TdofError(f"cannot reach the Ray cluster at {address}: {e.strerror or e}") from None


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}".rstrip(": ")


def _ray_reason(e: BaseException) -> str:
    """The first line of a Ray error that says what happened, without Ray's log excerpts."""
    for line in str(e).strip().splitlines():
        line = line.strip()
        if line and not line.startswith(("(", "[", "*")):
            return line.rstrip(".")[:200]
    return "no reason given"


def ray_init(address: str | None = None, num_cpus: int | None = None) -> bool:
    """Start a local Ray instance (``address`` None; ``num_cpus`` None = every core) or connect to
    the cluster at ``address``, unless Ray is up already in this process (a driver that started
    it, or a Ray task). True when this call started it (the caller then shuts it down).
    A cluster that cannot be reached -> TdofError "cannot reach the Ray cluster at ADDR: ..."."""
    try:
        import ray
    except ImportError:
        raise TdofError("executor 'ray' needs the ray package: pip install 'ray==2.60.0'") from None
    if ray.is_initialized():
        return False
    where = address or "a new local instance"
    if address:
        _probe(address)
    kwargs = {"log_to_driver": False}
    if not address:
        kwargs.update(include_dashboard=False, num_cpus=num_cpus)
    try:
        ray.init(address=address, **kwargs)
    except Exception as e:  # Ray raises ConnectionError, RuntimeError, ValueError ...
        raise TdofError(f"cannot reach the Ray cluster at {where}: {_first_line(e)}") from None
    return True


def _run_ray(fn: Callable, chunks: list, workers: int | None, address: str | None, advance) -> Iterator:
    scope = _SCOPE.get()
    in_scope = scope is not None and scope.executor == "ray"
    own = ray_init(address, scope.workers if in_scope else workers)
    if own and in_scope:
        scope.started_ray, own = True, False   # the scope shuts it down when it ends
    import ray

    running: dict = {}
    try:
        task = ray.remote(num_cpus=1)(_ray_task)
        fn_ref = ray.put(fn)
        limit = workers if workers else len(chunks)
        todo = iter(enumerate(chunks))
        for i, c in todo:
            running[task.remote(fn_ref, c)] = i
            if len(running) >= 2 * limit:
                break
        while running:
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                i = running.pop(ref)
                try:
                    result = pickle.loads(ray.get(ref))
                except ray.exceptions.RayTaskError as e:
                    cause = e.as_instanceof_cause()
                    if isinstance(cause, TdofError):
                        raise TdofError(str(cause)) from None
                    raise
                except ray.exceptions.RayError as e:
                    # the worker process died (killed: out of memory, a signal, a node lost) more
                    # often than Ray retries a task: one line, not Ray's exception and its logs
                    raise TdofError(f"a Ray worker died running chunk {i + 1} of {len(chunks)}, more often than "
                                    f"Ray retries a task ({type(e).__name__}: {_ray_reason(e)}); see the Ray "
                                    f"logs (/tmp/ray/session_latest/logs), and rerun: finished work is kept"
                                    ) from None
                nxt = next(todo, None)
                if nxt is not None:
                    running[task.remote(fn_ref, nxt[1])] = nxt[0]
                advance(chunks[i])
                yield result
    finally:
        for ref in running:
            try:
                ray.cancel(ref)
            except Exception:
                pass
        if own:
            ray.shutdown()


# ---------------------------------------------------------------------------------------------
# the entry point
# ---------------------------------------------------------------------------------------------
def resolve_workers(workers: int | None) -> int:
    """None -> the cores this process may run on (os.cpu_count(), less where an affinity mask or
    a container limits it); anything < 1 is an error."""
    if workers is None:
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except (AttributeError, OSError):
            return os.cpu_count() or 1
    if int(workers) < 1:
        raise TdofError(f"workers must be >= 1, got {workers}")
    return int(workers)


def run_chunks(fn: Callable[[Any], Any], chunks: Iterable, executor: str | None = None, workers: int | None = None,
               ray_address: str | None = None, progress: bool = False, description: str = "chunks",
               size: Callable[[Any], int] = lambda c: 1, unit: str = "it",
               start_method: str | None = None) -> Iterator[Any]:
    """Yield ``fn(chunk)`` for every chunk, as they finish (completion order).

    executor: "local" (worker processes; ``workers`` None = os.cpu_count(), 1 = in this process)
    or "ray" (``ray_address`` None starts a local Ray instance; ``workers`` then caps its CPUs
    and the tasks in flight); None: the innermost :func:`executor_scope`'s (and its
    ``ray_address`` when none is given), "local" outside any. ``progress``: a rich bar advanced by ``size(chunk)`` per finished
    chunk (e.g. ``size=len`` to count frames). An exception raised by ``fn`` stops the run and is
    raised here (the remaining chunks are cancelled); catch per-item errors inside ``fn``.
    A Ray cluster that cannot be reached -> TdofError "cannot reach the Ray cluster at ADDR: ...".
    """
    if executor is None:
        executor, scope_address = current_executor()
        ray_address = ray_address or scope_address
    if executor not in EXECUTORS:
        raise TdofError(f"executor must be one of {', '.join(EXECUTORS)}, got {executor!r}")
    chunks = list(chunks)
    with _progress(progress and bool(chunks), unit=unit) as bar:
        task = bar.add_task(description, total=sum(size(c) for c in chunks))

        def advance(c: Any) -> None:
            bar.advance(task, size(c))

        if executor == "ray":
            yield from _run_ray(fn, chunks, None if workers is None else resolve_workers(workers),
                                ray_address, advance)
            return
        n = min(resolve_workers(workers), len(chunks))
        if n <= 1:
            for c in chunks:
                result = fn(c)
                advance(c)
                yield result
            return
        yield from _run_local(fn, chunks, n, start_method, advance)


__all__ = ["EXECUTORS", "START_METHOD", "current_executor", "executor_scope", "process_cache", "ray_init",
           "resolve_workers", "run_chunks"]
