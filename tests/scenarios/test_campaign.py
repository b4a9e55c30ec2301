"""The shared campaign helper (scenarios/campaign.py): task-order folding, exactly-once counting,
bounded in-flight work; and a small launcher campaign on threads vs a 2-process Dask LocalCluster,
including one whose worker is killed mid-campaign."""
import os
import signal
import threading
import time
from concurrent.futures import Future

import numpy as np
import pytest

from symkf.scenarios import campaign as H
from symkf.scenarios.launcher import campaign as C


class LostWorker(Exception):
    pass


class ShuffledExecutor:
    """Completes in-flight tasks in reverse order; the first attempt of task 2 is 'lost'."""

    workers, name = 2, "shuffled"
    lost_errors = (LostWorker,)

    def __init__(self):
        self.attempts, self.max_in_flight, self._in_flight = {}, 0, set()

    def submit(self, task):
        future = Future()
        index = task.args[0]
        self.attempts[index] = self.attempts.get(index, 0) + 1
        if index == 2 and self.attempts[index] == 1:
            future.set_exception(LostWorker())
        else:
            future.set_result(task.function(*task.args))
        self._in_flight.add(future)
        self.max_in_flight = max(self.max_in_flight, len(self._in_flight))
        return future

    def wait_any(self, futures):
        chosen = list(futures)[-1]
        self._in_flight.discard(chosen)
        return [chosen]

    @staticmethod
    def result(future):
        return future.result()


def square(i):
    return i * i


def test_results_fold_in_task_order_exactly_once_with_a_bounded_window():
    tasks = [H.Task(f"t{i}", square, (i,), runs=2) for i in range(10)]
    folded, progress = [], []
    executor = ShuffledExecutor()
    stats = H.run_campaign(tasks, lambda task, r: folded.append((task.label, r)), executor=executor,
                           window=3, progress=lambda done, total: progress.append((done, total)))
    assert folded == [(f"t{i}", i * i) for i in range(10)]
    assert stats.tasks == 10 and stats.runs == 20 and stats.resubmitted == 1 and executor.attempts[2] == 2
    assert executor.max_in_flight <= 3
    assert progress[0] == (0, 20) and progress[-1] == (20, 20)
    assert [d for d, _ in progress] == sorted(d for d, _ in progress)


def test_run_streams_are_keyed_not_sequential():
    a = H.run_rng(5, 20, 1, 7).normal(size=3)
    np.testing.assert_array_equal(a, H.run_rng(5, 20, 1, 7).normal(size=3))
    assert not np.array_equal(a, H.run_rng(5, 20, 1, 8).normal(size=3))
    assert [len(r) for r in H.chunks(12, 5)] == [5, 5, 2]


def test_scheduler_arguments_are_checked():
    assert H.scheduler_problem(None, None) is None and H.scheduler_problem("local:2", None) is None
    assert "local:N" in H.scheduler_problem("local:0", None)
    assert "tcp://" in H.scheduler_problem("somehost", None)
    assert "--workers" in H.scheduler_problem(None, 0)
    with pytest.raises(ValueError):
        H.make_executor("local:x")


def test_a_worker_refuses_a_model_it_cannot_reproduce(launcher_compiled):
    with pytest.raises(RuntimeError, match="content hash"):
        H.compiled_model(H.ModelKey("launcher", "0" * 64))


# ---------------------------------------------------------------------- Dask
RUNS, SEED, DURATION = 10, 17, 60.0


def per_run_tables(results):
    return {(r.case.label, f): r.per_run(f) for r in results for f in C.FILTERS}


@pytest.fixture(scope="module")
def cluster(launcher_compiled):
    pytest.importorskip("distributed", reason="dask[distributed] is not installed (pip install 'symkf[dask]')")
    with H.local_cluster(2) as c:                # the cluster --scheduler local:2 makes
        yield c


@pytest.fixture(scope="module")
def on_threads(launcher_compiled):
    return C.Campaign(RUNS, SEED, rates=(20,), duration=DURATION, workers=2, chunk_runs=5).run()


def test_dask_local_cluster_gives_bit_identical_per_run_results(cluster, on_threads):
    executor = H.DaskExecutor(cluster.scheduler_address)
    try:
        campaign = C.Campaign(RUNS, SEED, rates=(20,), duration=DURATION, chunk_runs=5)
        on_dask = campaign.run(executor)
    finally:
        executor.close()
    assert campaign.stats.executor.startswith("dask") and campaign.stats.workers == 2
    threads, dask = per_run_tables(on_threads), per_run_tables(on_dask)
    for key in threads:
        assert threads[key].shape == (RUNS, len(C.PER_RUN_COLUMNS))
        np.testing.assert_array_equal(threads[key], dask[key])
    for a, b in zip(on_threads, on_dask):
        for f in C.FILTERS:
            np.testing.assert_array_equal(a.errors[f].rms(), b.errors[f].rms())
            np.testing.assert_array_equal(a.errors[f].mean_nees(), b.errors[f].mean_nees())


def test_a_worker_computes_each_flight_once_and_loads_the_model_once(cluster, on_threads):
    """Many tasks per worker: each worker computes a rate's truth and radar track at most once and
    loads the model at most once (per-process caches keyed by their inputs and by the build's
    content hash; a forked worker starts with what this process had); the workers run under the
    LocalCluster settings that spare CPU (no malloc trim threshold)."""
    executor = H.DaskExecutor(cluster.scheduler_address)
    try:
        campaign = C.Campaign(RUNS, SEED, rates=(20, 10), duration=DURATION, chunk_runs=1)
        before = executor.client.run(lambda: C._case_flight.cache_info().misses)
        campaign.run(executor)
        caches = executor.client.run(lambda: (C._case_flight.cache_info(), sorted(map(str, H._MODELS)),
                                              os.environ.get("MALLOC_TRIM_THRESHOLD_")))
    finally:
        executor.close()
    assert len(caches) == 2 and len(campaign.tasks()) == 4 * RUNS
    for worker, (flights, models, trim) in caches.items():
        assert flights.misses - before[worker] <= 2           # at most one truth per rate, never recomputed
        assert flights.hits + flights.misses >= 1
        assert str(campaign.model_key) in models
        assert trim is None


def test_a_local_cluster_campaign_counts_its_workers_cpu(launcher_compiled):
    pytest.importorskip("distributed", reason="dask[distributed] is not installed (pip install 'symkf[dask]')")
    campaign = C.Campaign(2, SEED, rates=(20,), duration=DURATION, scheduler="local:1", chunk_runs=1)
    results = campaign.run()
    task_cpu = sum(r.task_cpu_s for r in results)      # spent in the worker process only
    assert task_cpu > 0 and campaign.stats.cpu_s >= task_cpu


def test_a_worker_killed_mid_campaign_loses_no_run_and_counts_none_twice(cluster, on_threads):
    executor = H.DaskExecutor(cluster.scheduler_address)
    # One run per task: when the first result is folded, many tasks are still queued or running,
    # so a busy worker exists however fast the machine (run streams are keyed by run, not chunk).
    campaign = C.Campaign(RUNS, SEED, rates=(20,), duration=DURATION, chunk_runs=1)
    tasks = campaign.tasks()
    killed = {}
    lock = threading.Lock()

    def busy_workers(timeout=10.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            busy = [w for w, keys in executor.client.processing().items() if keys]
            if busy:
                return busy
            time.sleep(0.01)
        return []

    def kill_a_busy_worker(task, chunk):
        with lock:
            if not killed:
                busy = busy_workers()
                assert busy, "no task in flight to lose: make the test's runs longer"
                pid = executor.client.run(os.getpid, workers=[busy[0]])[busy[0]]
                os.kill(pid, signal.SIGKILL)
                killed.update(worker=busy[0], pid=pid)
        fold(task, chunk)

    results = {case: C.CaseResult.empty(case, C.flight_times(case.rate_hz, DURATION)) for case in campaign.cases}

    def fold(task, chunk):
        result = results[task.args[1]]
        for f in C.FILTERS:
            result.errors[f].merge(chunk.errors[f])
            result.add_per_run(f, chunk.per_run[f])
    try:
        stats = H.run_campaign(tasks, kill_a_busy_worker, executor=executor, window=len(tasks))
    finally:
        executor.close()
    assert killed and stats.tasks == len(tasks) and stats.runs == 2 * RUNS
    threads = per_run_tables(on_threads)
    for case, result in results.items():
        for f in C.FILTERS:
            table = result.per_run(f)
            np.testing.assert_array_equal(table[:, 0], np.arange(RUNS))      # every run once, in order
            np.testing.assert_array_equal(table, threads[(case.label, f)])
            assert result.errors[f].runs == RUNS


# ---------------------------------------------------------------------- the launcher's tasks
def test_a_task_reuses_its_filters_and_each_run_is_the_run_computed_alone(launcher_compiled):
    """run_chunk builds each filter once and resets x, P per run: the rows (and sums) of runs
    0-2 in one task equal those of the three runs as one-run tasks, bit for bit."""
    campaign = C.Campaign(3, SEED, rates=(20,), duration=30.0)
    args = (campaign.model_key, C.Case(20, "large"), SEED)
    together = C.run_chunk(*args, (0, 3), 30.0, campaign.tuning)
    alone = [C.run_chunk(*args, (run, run + 1), 30.0, campaign.tuning) for run in range(3)]
    for f in C.FILTERS:
        np.testing.assert_array_equal(together.per_run[f], np.vstack([a.per_run[f] for a in alone]))
        assert together.per_run[f][:, 4].std() > 0                   # the runs differ (mean NEES)
        np.testing.assert_array_equal(together.errors[f].nees, sum(a.errors[f].nees for a in alone))
        assert 0 < together.cpu_s[f] <= together.task_cpu_s


def test_tasks_put_the_longest_cases_first_and_results_keep_the_asked_order(launcher_compiled):
    campaign = C.Campaign(4, SEED, rates=(10, 20), duration=5.0, chunk_runs=2)
    assert [t.args[1].rate_hz for t in campaign.tasks()] == [20] * 4 + [10] * 4
    assert [t.args[3] for t in campaign.tasks()][:2] == [(0, 2), (2, 4)]
    results = campaign.run()
    assert [r.case.label for r in results] == ["10Hz small", "10Hz large", "20Hz small", "20Hz large"]
    assert all(r.per_run(f)[:, 0].tolist() == [0, 1, 2, 3] for r in results for f in C.FILTERS)


def test_station_parameters_per_step_are_the_model_s_rows():
    from symkf.models import launcher as L
    from symkf.scenarios.launcher.truth import station_params
    stations = [1, 1, 2, 3, 3, 2, 1]
    for measurement, row in (("radar", L.station_params), ("radar_wgs84", L.station_params_wgs84)):
        np.testing.assert_array_equal(station_params(stations, measurement), np.array([row(s) for s in stations]))
    with pytest.raises(ValueError, match="measurement"):
        station_params(stations, "lidar")


def test_a_campaign_on_a_whole_o3_build_gives_the_default_build_s_numbers(launcher_compiled):
    """Campaign(build=...) runs another build folder (here every unit at -O3, IEEE only) with the
    same per-run results, bit for bit, as the campaign's default build (its lockstep loops only)."""
    o3 = C.Campaign(2, SEED, rates=(20,), duration=30.0, build={"optimization": "-O3 -fno-math-errno"})
    default = C.Campaign(2, SEED, rates=(20,), duration=30.0)
    assert dict(default.model_key.overrides) == C.LOCKSTEP_BUILD
    assert dict(o3.model_key.overrides) == {**C.LOCKSTEP_BUILD, "optimization": "-O3 -fno-math-errno"}
    assert o3.model_key.content_hash != default.model_key.content_hash
    for a, b in zip(o3.run(), default.run()):
        for f in C.FILTERS:
            np.testing.assert_array_equal(a.per_run(f), b.per_run(f))


def test_an_exact_campaign_is_one_run_at_a_time_bit_for_bit_and_the_default_within_round_off(launcher_compiled):
    """exact=True: the lockstep lanes call libm, every per-run row is that of the runs stepped one
    at a time (no lockstep loops) bit for bit; the default (libmvec in the prediction) differs
    from it by round-off only over these 30 s."""
    exact = C.Campaign(5, SEED, rates=(20,), duration=30.0, exact=True)
    alone = C.Campaign(5, SEED, rates=(20,), duration=30.0, build={"ekf_lockstep": False, "ukf_lockstep": False})
    default = C.Campaign(5, SEED, rates=(20,), duration=30.0)
    assert dict(exact.model_key.overrides) == C.EXACT_LOCKSTEP_BUILD
    for a, b, c in zip(exact.run(), alone.run(), default.run()):
        for f in C.ESTIMATES:
            np.testing.assert_array_equal(a.per_run(f), b.per_run(f))
            assert not np.array_equal(a.per_run(f), c.per_run(f))
            counts = [C.PER_RUN_COLUMNS.index(n) for n in ("run", "failed_steps", "diverged", "excursion")]
            np.testing.assert_array_equal(c.per_run(f)[:, counts], a.per_run(f)[:, counts])
            squared = [i for i, n in enumerate(C.PER_RUN_COLUMNS) if n.startswith("mean_sq_error_")]
            np.testing.assert_allclose(c.per_run(f)[:, squared], a.per_run(f)[:, squared], rtol=2e-6, atol=0)


def test_progress_bar_uses_tqdm_on_a_terminal_and_its_own_lines_in_a_log():
    import io
    pytest.importorskip("tqdm", reason="tqdm is not installed (pip install -e '.[test]')")
    from symkf.scenarios.campaign import ProgressBar

    class Terminal(io.StringIO):
        def isatty(self):
            return True
    screen = Terminal()
    bar = ProgressBar(stream=screen)
    for done in (0, 3, 10):
        bar(done, 10)
    assert bar._bar is not None and bar._bar.n == 10 and "Monte Carlo" in screen.getvalue()
    assert "10/10" in screen.getvalue()
    log = io.StringIO()
    bar = ProgressBar(stream=log)
    bar.start -= 100.0                                # e.g. a build between making the bar and the campaign
    for done in range(11):
        bar(done, 10)
    assert float(log.getvalue().split("runs, ")[1].split(" s")[0]) < 50      # timed from the campaign's start
    lines = log.getvalue().splitlines()
    assert bar._bar is None and len(lines) == 10 and lines[-1].startswith("[" + "#" * 40 + "] 10/10 runs")
