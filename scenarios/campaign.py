"""Monte Carlo campaigns on local threads or on a Dask cluster: one helper for every paper.

A campaign is a list of :class:`Task` s. Each task is a module-level function of plain arguments
that draws from its own random stream (:func:`run_rng`, keyed by the campaign seed, the case and
the run index), so its result does not depend on where or when it runs. :func:`run_campaign`
hands the tasks to an executor and *folds* each result into the caller's accumulators in task
order, as results arrive:

- same seed -> bit-identical per-run results and totals, whatever the executor and worker count
  (results that arrive early wait in a small re-order buffer; sums are formed in one order);
- at most ``window`` tasks are in flight, so peak client memory does not grow with the run count
  (a task returns sums and per-run summaries, never a run's history);
- a task whose worker died is computed again (Dask reschedules it; if Dask gives up with
  ``KilledWorker`` it is resubmitted) and every task is folded exactly once;
- ``progress(done, total)`` is called with the number of completed runs.

Executors: ``scheduler=None`` runs on local threads (the generated C releases the GIL; nothing
else to install); ``"local:N"`` starts a ``distributed.LocalCluster`` of N single-threaded worker
processes (:func:`local_cluster`: without the Dask defaults that cost a campaign CPU and change
no result); ``"tcp://host:8786"`` (or any Dask address) uses a running cluster. Workers get the
compiled model by its *content hash* (:func:`compiled_model`): each builds or loads it from its own
cache on first use and refuses to run if its sources give a different hash; no library is pickled.
"""
from __future__ import annotations

import os
import sys
import threading
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

try:
    import resource
except ImportError:                            # Windows
    resource = None


# ---------------------------------------------------------------------- random streams, models
def run_rng(seed: int, *key: int) -> np.random.Generator:
    """The random stream of one run: ``SeedSequence([seed, *key])`` (key = case ids, run index).

    A function of (seed, key) only, so a run draws the same numbers in any process, in any order,
    and whichever other cases or runs the campaign includes.
    """
    return np.random.default_rng(np.random.SeedSequence([int(seed), *(int(k) for k in key)]))


@dataclass(frozen=True)
class ModelKey:
    """A compiled model named by its content hash (what a worker needs to find or build it) and
    the codegen overrides of its configuration (sorted (key, value) pairs; () for the defaults)."""

    name: str
    content_hash: str
    overrides: tuple = ()


_MODELS: dict[ModelKey, Any] = {}
_MODELS_LOCK = threading.Lock()


def model_key(name: str, **overrides) -> ModelKey:
    """Build (if stale) and load ``name`` with codegen ``overrides`` here; return the key tasks
    carry to the workers."""
    model = _load(name, **overrides)
    key = ModelKey(name, _content_hash(model), tuple(sorted(overrides.items())))
    with _MODELS_LOCK:
        _MODELS.setdefault(key, model)
    return key


def compiled_model(key: ModelKey):
    """The compiled model with ``key.content_hash``, built or loaded from this process's own cache
    on first use (then kept for the process). Raises if this installation generates a different
    hash: the worker runs other symkf/model sources, CasADi or compiler than the client."""
    model = _MODELS.get(key)
    if model is not None:
        return model
    with _MODELS_LOCK:
        if key not in _MODELS:
            model = _load(key.name, **dict(key.overrides))
            found = _content_hash(model)
            if found != key.content_hash:
                raise RuntimeError(
                    f"model '{key.name}': this worker builds content hash {found[:12]}, the client asked for "
                    f"{key.content_hash[:12]}; install the same symkf sources, CasADi and compiler on every worker")
            _MODELS[key] = model
        return _MODELS[key]


def _load(name: str, **overrides):
    from symkf.runtime import load
    return load(name, **overrides)


def _content_hash(model) -> str:
    manifest = getattr(model.backend, "manifest", None)
    if manifest is None:                       # the CasADi-VM fallback has no library: hash its kind
        return f"casadi-vm:{model.name}"
    return manifest["content_hash"]


# ---------------------------------------------------------------------- tasks and executors
@dataclass(frozen=True)
class Task:
    """One unit of work: ``function(*args)``, worth ``runs`` Monte Carlo runs on the progress bar."""

    label: str
    function: Callable
    args: tuple
    runs: int = 1


@dataclass
class CampaignStats:
    """What the executor did: tasks folded, tasks computed again after a worker was lost."""

    executor: str
    workers: int
    tasks: int = 0
    runs: int = 0
    resubmitted: int = 0
    wall_s: float = 0.0
    #: CPU seconds (user + system) of this process and of the processes it started and waited
    #: for meanwhile: a LocalCluster's scheduler, nannies and workers when the campaign made the
    #: executor (``scheduler="local:N"``); a running cluster's workers are not counted
    cpu_s: float = 0.0
    folded: list[str] = field(default_factory=list)


class ThreadExecutor:
    """Tasks on local threads (the default; the compiled C releases the GIL)."""

    def __init__(self, workers: int | None = None):
        self.workers = max(1, workers or os.cpu_count() or 1)
        self.name = f"threads:{self.workers}"
        self._pool = ThreadPoolExecutor(self.workers)
        self.lost_errors: tuple[type[BaseException], ...] = ()

    def submit(self, task: Task):
        return self._pool.submit(task.function, *task.args)

    def wait_any(self, futures):
        return wait(futures, return_when=FIRST_COMPLETED).done

    @staticmethod
    def result(future):
        return future.result()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor:
    """Tasks on a Dask cluster: ``local:N`` (a LocalCluster of N processes) or a scheduler address."""

    def __init__(self, scheduler: str):
        try:
            from distributed import Client
            from distributed.scheduler import KilledWorker
        except ImportError:
            raise SystemExit("--scheduler needs Dask: pip install 'symkf[dask]' (dask[distributed])") from None
        self.cluster = None
        if scheduler.startswith("local:"):
            workers = _positive_int(scheduler.split(":", 1)[1], scheduler)
            self.cluster = local_cluster(workers)
            self.client = Client(self.cluster)
        else:
            try:
                self.client = Client(scheduler, timeout="20s")
            except (OSError, TimeoutError) as exc:
                raise SystemExit(f"--scheduler {scheduler}: no Dask scheduler answered ({exc}); start one with "
                                 "`dask scheduler` and workers with `dask worker ADDRESS`, or use local:N") from None
        self.workers = max(1, len(self.client.scheduler_info(n_workers=-1)["workers"]))
        self.name = f"dask:{scheduler}"
        self.lost_errors = (KilledWorker,)
        self._campaign = uuid.uuid4().hex[:8]

    def submit(self, task: Task):
        key = f"symkf-{task.label}-{self._campaign}-{uuid.uuid4().hex[:6]}"
        return self.client.submit(task.function, *task.args, key=key, pure=False)

    def wait_any(self, futures):
        from distributed import wait as dask_wait
        return dask_wait(list(futures), return_when="FIRST_COMPLETED").done

    @staticmethod
    def result(future):
        try:
            return future.result()
        finally:
            future.release()

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


#: Dask settings of a LocalCluster made for a campaign (``local:N``). Dask's defaults cost CPU
#: and buy a campaign nothing; none of these changes a task, its inputs or the fold order:
#:
#: - the event loops' 20 ms tick, the 500 ms system monitor and the 100 ms memory monitor: an idle
#:   2-worker cluster used 0.078 CPU-s per second of wall time with them, 0.013 with these (paid
#:   for the whole campaign, so a loaded machine, whose campaigns last longer, pays more);
#: - the workers' statistical profiler, which samples the task thread every 10 ms;
#: - ``MALLOC_TRIM_THRESHOLD_`` in the workers' environment (:func:`local_cluster`).
LOCAL_CLUSTER_CONFIG = {
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.worker.profile.enabled": False,
    # Linux: a worker is a fork of this process, which has imported symkf, CasADi, NumPy and Dask
    # already (a spawned one imports them again: about 1.3 CPU-s a worker, 14-18 % of a 400-run
    # launcher campaign on two). Elsewhere Python's own default (spawn: fork is unsafe on macOS).
    **({"distributed.worker.multiprocessing-method": "fork"} if sys.platform.startswith("linux") else {}),
}


def local_cluster(workers: int):
    """A LocalCluster of ``workers`` single-threaded worker processes, no dashboard, with
    :data:`LOCAL_CLUSTER_CONFIG` (start a cluster of your own and pass its address to watch a
    dashboard).

    The workers' environment goes without Dask's ``MALLOC_TRIM_THRESHOLD_``: setting it switches
    off glibc's adaptive mmap threshold, so every array above 128 kB (a run's state and covariance
    histories) is a fresh mmap whose pages fault in again: 730k minor page faults instead of
    50-70k and 1.5 s more system time for 80 launcher runs on one worker.
    """
    import dask
    from distributed import LocalCluster
    environ = {name: value for name, value in dask.config.get("distributed.nanny.pre-spawn-environ").items()
               if name != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({**LOCAL_CLUSTER_CONFIG, "distributed.nanny.pre-spawn-environ": environ}):
        # read by the scheduler, each nanny and (passed on by its nanny) each worker as they are made
        # no dashboard; the scheduler's small HTTP service (health, metrics) on a free port
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            scheduler_kwargs={"dashboard": False, "dashboard_address": ":0"})


def _positive_int(text: str, scheduler: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise ValueError(f"--scheduler {scheduler!r}: expected local:N with N >= 1 workers")
    return value


def scheduler_problem(scheduler: str | None, workers: int | None) -> str | None:
    """What is wrong with ``--scheduler``/``--workers`` (None if nothing), checked before any work."""
    if workers is not None and workers < 1:
        return f"--workers must be >= 1, got {workers}"
    if scheduler is None:
        return None
    if scheduler.startswith("local:"):
        count = scheduler.split(":", 1)[1]
        return None if count.isdigit() and int(count) >= 1 else f"--scheduler {scheduler!r}: expected local:N with N >= 1"
    if "://" not in scheduler:
        return f"--scheduler {scheduler!r}: expected local:N or a Dask address such as tcp://host:8786"
    return None


def make_executor(scheduler: str | None = None, workers: int | None = None):
    """Local threads (``scheduler=None``), a LocalCluster (``local:N``) or a Dask scheduler address."""
    problem = scheduler_problem(scheduler, workers)
    if problem:
        raise ValueError(problem)
    return ThreadExecutor(workers) if scheduler is None else DaskExecutor(scheduler)


def add_scheduler_arguments(parser, default_workers: int | None = None) -> None:
    """``--scheduler`` and ``--workers`` for a ``compare`` command."""
    parser.add_argument("--scheduler", default=None,
                        help="run the Monte Carlo on Dask: local:N (a LocalCluster of N processes) or a "
                             "scheduler address tcp://HOST:8786 (default: local threads)")
    parser.add_argument("--workers", type=int, default=default_workers,
                        help="local threads when no --scheduler is given (default: "
                             f"{default_workers or 'one per core'})")


# ---------------------------------------------------------------------- the campaign loop
def run_campaign(tasks: Sequence[Task], fold: Callable[[Task, Any], None], scheduler: str | None = None,
                 workers: int | None = None, progress: Callable[[int, int], None] | None = None,
                 executor=None, window: int | None = None, max_resubmits: int = 3) -> CampaignStats:
    """Run ``tasks``; call ``fold(task, result)`` once per task, in task order.

    ``executor`` (an object from :func:`make_executor`) is used and left open if given; otherwise
    one is made from ``scheduler``/``workers`` and closed at the end. ``window`` bounds the tasks
    in flight (default: 4 per worker).
    """
    cpu = cpu_seconds()
    own = executor is None
    executor = make_executor(scheduler, workers) if own else executor
    try:
        stats = _run(list(tasks), fold, executor, progress or (lambda done, total: None),
                     window or 4 * executor.workers, max_resubmits)
    finally:
        if own:
            executor.close()
    stats.cpu_s = cpu_seconds() - cpu
    return stats


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and of its children that have ended (all their
    threads; a LocalCluster's worker processes once it is closed)."""
    if resource is None:                       # not on a POSIX system: this process only
        return time.process_time()
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _run(tasks: list[Task], fold, executor, progress, window: int, max_resubmits: int) -> CampaignStats:
    stats = CampaignStats(executor.name, executor.workers)
    total_runs = sum(t.runs for t in tasks)
    start = time.perf_counter()
    in_flight: dict[Any, int] = {}
    arrived: dict[int, Any] = {}
    resubmits = [0] * len(tasks)
    next_submit = next_fold = 0
    progress(0, total_runs)
    while next_fold < len(tasks):
        while next_submit < len(tasks) and next_submit < next_fold + window:
            in_flight[executor.submit(tasks[next_submit])] = next_submit
            next_submit += 1
        for future in executor.wait_any(list(in_flight)):
            index = in_flight.pop(future)
            try:
                arrived[index] = executor.result(future)
            except executor.lost_errors:
                if resubmits[index] >= max_resubmits:
                    raise
                resubmits[index] += 1
                stats.resubmitted += 1
                in_flight[executor.submit(tasks[index])] = index
        while next_fold in arrived:
            task = tasks[next_fold]
            fold(task, arrived.pop(next_fold))
            stats.tasks += 1
            stats.runs += task.runs
            stats.folded.append(task.label)
            next_fold += 1
            progress(stats.runs, total_runs)
    stats.wall_s = time.perf_counter() - start
    return stats


class ProgressBar:
    """Progress over completed runs on stderr: a ``tqdm.auto`` bar when tqdm is installed and
    stderr is a terminal or a Jupyter notebook (its widget there, with ipywidgets); else a
    one-line bar of its own (a line per 10 % when stderr is not a terminal, e.g. a log)."""

    def __init__(self, width: int = 40, stream=None, use_tqdm: bool | None = None):
        self.width, self.start = width, time.perf_counter()
        self.stream = stream or sys.stderr
        self.interactive = self.stream.isatty()
        self._decile = 0
        self._tqdm = self._tqdm_class(self.interactive) if use_tqdm is not False else None
        self._bar = None

    def __call__(self, done: int, total: int) -> None:
        if done == 0:                          # the campaign starts (a build before it is not its time)
            self.start = time.perf_counter()
        if total <= 0 or done == 0:
            return
        if self._tqdm is not None and self._tqdm_update(done, total):
            return
        filled = int(self.width * done / total)
        elapsed = time.perf_counter() - self.start
        text = f"[{'#' * filled}{'.' * (self.width - filled)}] {done}/{total} runs, {elapsed:.1f} s"
        if self.interactive:
            self.stream.write("\r" + text + ("\n" if done == total else ""))
        elif done == total or (10 * done) // total > self._decile:
            self.stream.write(text + "\n")
        self._decile = (10 * done) // total
        self.stream.flush()

    @staticmethod
    def _tqdm_class(terminal: bool):
        """tqdm.auto's bar if tqdm is installed and it has somewhere to draw (a terminal, a notebook)."""
        try:
            from tqdm.auto import tqdm
        except ImportError:
            return None
        notebook = any(base.__module__ == "tqdm.notebook" for base in tqdm.__mro__)      # Jupyter's widget bar
        return tqdm if terminal or notebook else None

    def _tqdm_update(self, done: int, total: int) -> bool:
        """Move the tqdm bar; False (use the plain bar) if it cannot be drawn here."""
        if self._bar is None:
            try:
                self._bar = self._tqdm(total=total, unit="run", desc="Monte Carlo", file=self.stream)
            except ImportError:                 # tqdm.notebook without ipywidgets
                self._tqdm = None
                return False
        self._bar.update(done - self._bar.n)
        if done >= total:
            self._bar.close()
        return True


def chunks(runs: int, size: int) -> list[range]:
    """Run indices 0..runs-1 in consecutive ranges of ``size`` (the last may be shorter). The chunk
    size, not the worker count, fixes how per-run sums are grouped, so totals do not depend on it."""
    return [range(start, min(start + size, runs)) for start in range(0, runs, size)]


__all__ = ["CampaignStats", "DaskExecutor", "ModelKey", "ProgressBar", "Task", "ThreadExecutor",
           "add_scheduler_arguments", "chunks", "compiled_model", "cpu_seconds", "LOCAL_CLUSTER_CONFIG", "local_cluster", "make_executor", "model_key",
           "run_campaign", "run_rng", "scheduler_problem"]
