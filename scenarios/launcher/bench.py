"""µs per EKF/UKF predict+update step of the KSLV-I launcher filters (paper 004), path by path.

    symkf bench launcher [--json] [--steps N] [--reference-steps N] [--campaign] [--instructions]

Paths (rows ``{"filter", "path", "us_per_step", ...}``):
- ``numpy_reference``: runtime/reference/ (NumPy algebra, model through CasADi calls);
- ``compiled_step``: ``Filter.step`` — one C call per step from Python (the C fast path of
  runtime/fastcall.py: checks, copies and kernel call in one call), each step's inputs ready as a
  measurement arrives (t a float, z and q arrays of their own), prepared before the timing as the
  C loop reads its inputs before its timing;
- ``compiled_step_rows``: the same calls with t, z and q indexed from the (N, 3) record inside
  the timed loop (three numpy indexings, ~0.1 µs each: the loop's cost, not the call's);
- ``compiled_step_python``: the calls of ``compiled_step`` with the fast path off
  (``filter.fast_path = False``): every call through the Python contract;
- ``c_loop``: the same generated ``launcher_<filter>_step_radar`` called in a C loop (no Python
  per step) over the same record, compiled against build/launcher/ with the library's flags and
  loaded into this process (ctypes, one call per batch of 100 steps);
- ``c_loop_process``: the same C loop as a program of its own (the harness ``--instructions``
  counts), its wall and CPU time measured by the program itself;
- ``compiled_run``: per step inside one ``launcher_<filter>_step_radar_run`` call;
- ``filterpy`` (when FilterPy is installed, ``pip install -e .[bench]``): FilterPy's EKF and UKF
  on the same model, calling our compiled f_d, F, h, H, with the same kappa.
Every path is timed in each of ``ROUNDS`` interleaved rounds (:func:`time_paths`): the step
paths and ``c_loop`` in alternate batches of 100 steps, then a share of each other path, so
that every figure sees the same machine load; each figure is the median over rounds, of wall
time and of the timing thread's CPU time (the CPU column: what a path costs, whatever else the
machine runs; a long call such as a whole run is preempted on a loaded machine, so its wall time
is the load's as much as its own). The printout states the load average before and after.
``--campaign`` adds ``campaign_wall_s``: the wall time of the default ``compare`` campaign (4 cases
x 100 runs x both filters; ``--scheduler`` runs it on Dask; tables and figures not included), its
throughput per worker, its CPU seconds split into the compiled runs and the rest, and the library
it ran (content hash, -O flags).
``--instructions`` counts, with callgrind, the instructions of one call of each part (predict,
update, the fused step, a step inside the run loop, a backward step of the RTS smoother's
``<filter>_smooth_run`` over that run, and a run-step of 4 runs stepped in lockstep in AVX2
vectors: ``Filter.run_lockstep``, the campaign's loop, with libmvec in the prediction and, exact,
with libm lane by lane; and the same for a backward step), with where a step's instructions go
(wrapper, run loop, propagation, h and H, predict and update kernels, libm), and the UKF step of
the build with SIMD lanes (``ukf_lanes=True``: four sigma points at a time in AVX2 lanes; the
default library, like the flight bundle, computes them one at a time) in the row "SIMD lanes".
"""
from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from symkf.codegen import build_model
from symkf.models import launcher as L
from symkf.runtime import load
from symkf.runtime.reference import ReferenceFilter
from symkf.scenarios import callgrind, timing
from symkf.scenarios.campaign import compiled_model
from symkf.scenarios.report import emit
from .campaign import EXACT_LOCKSTEP_BUILD, LOCKSTEP_BUILD, LOCKSTEP_RUNS, TUNING, Campaign, initial_estimate, Case
from .truth import propagate, radar_track

FILTERS = ("ekf", "ukf")
RATE_HZ = 20
#: The C loop of ``c_loop_process`` and of ``--instructions``, a program of its own (stdin: the record).
C_LOOP = "c_loop_driver.c"
#: The C loop of ``c_loop``, called in-process one batch at a time (:class:`CLoop`).
C_LOOP_BATCH = "c_loop_batch.c"


def add_arguments(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print the JSON object only")
    parser.add_argument("--steps", type=int, default=10000, help="steps per compiled path (default 10000)")
    parser.add_argument("--reference-steps", type=int, default=10000,
                        help="steps for the NumPy reference and FilterPy (default 10000)")
    parser.add_argument("--campaign", action="store_true", help="also time the default compare campaign")
    parser.add_argument("--instructions", action="store_true",
                        help="also count instructions per C-loop step with valgrind (deterministic)")
    parser.add_argument("--scheduler", default=None,
                        help="run --campaign on Dask (local:N or tcp://HOST:PORT; default: local threads)")


def run(args) -> int:
    report = measure(args.steps, args.reference_steps, args.campaign, args.instructions, args.scheduler)
    emit(report, None, args.json, lambda r: print(human_table(r)))
    return 0


# ---------------------------------------------------------------------- workload
class Workload:
    """A 20 Hz flight segment (truth, radar draws, stations) repeated to any length."""

    def __init__(self, steps: int):
        times = np.arange(int(L.T_INSERTION * RATE_HZ) + 1) / RATE_HZ
        truth = propagate(times)
        track = radar_track(times, truth)
        self.base_times, self.truth = times, truth
        self.z, self.q = track.noisy(np.random.default_rng(0)), track.station_params()
        self.steps = steps
        self.x0, self.P0 = initial_estimate(Case(RATE_HZ, "small"), truth[0])

    def index(self, k: int) -> int:
        return 1 + k % (len(self.base_times) - 1)


def _options(family: str) -> dict:
    """The paper's filters: no innovation gate (paper 004 fuses every sample), kappa for the UKF."""
    return {"gate": "none", **({"kappa": TUNING["kappa"]} if family == "ukf" else {})}


#: Rounds (medians over rounds; the spread of the rounds' ratios is reported).
ROUNDS = 5
#: Steps per round and path, at least (``--steps`` / ROUNDS if larger): 10 batches of 100.
MIN_ROUND_STEPS = 1000


def time_paths(model, work: Workload, reference_steps: int) -> tuple[dict[str, dict[str, timing.Samples]], dict]:
    """Every path of both filters in :data:`ROUNDS` interleaved rounds, so that every path sees
    the machine load of every round (this shared 2-core machine swings between ~2.0 and ~3.6 µs
    for the same C EKF step as other jobs come and go; a path timed on its own reads whatever
    load its moment had). A round runs, per filter, the step paths and the in-process C loop in
    alternate batches of 100 steps (:func:`time_compiled_step`, so compiled_step / c_loop compares
    batches taken under the same load), then one share of each other path (:func:`round_shares`:
    whole compiled runs, the NumPy reference, FilterPy, the C loop as a program of its own).
    Per path: wall and this thread's CPU seconds per step of each round (medians over the
    rounds are the figures); the spread: per filter and round, compiled_step / c_loop and
    compiled_step / c_loop_process."""
    steps = max(MIN_ROUND_STEPS, work.steps // ROUNDS)
    directory = build_model("launcher").directory
    with tempfile.TemporaryDirectory() as tmp:
        loop = CLoop(work, directory, Path(tmp))
        program = CLoopProgram(_compile_c_loop(directory, Path(tmp)), _c_loop_input(work), steps)
        shares = {family: round_shares(model, family, work, steps, reference_steps, program) for family in FILTERS}
        rounds = []
        for i in range(ROUNDS):
            figures = {}
            for family in FILTERS:
                batches = time_compiled_step(model, family, work, steps=steps, c_loop=loop)
                figures[family] = {path: (b.median, b.cpu_median) for path, b in batches.items()}
                figures[family].update({path: share(i) for path, share in shares[family].items()})
            rounds.append(figures)
    samples = {family: timing.from_rounds([r[family] for r in rounds]) for family in FILTERS}
    spread = {f"{family} compiled_step/{loop_path}": timing.round_ratios(samples[family]["compiled_step"],
                                                                         samples[family][loop_path])
              for family in FILTERS for loop_path in ("c_loop", "c_loop_process")}
    return samples, spread


def round_shares(model, family: str, work: Workload, steps: int, reference_steps: int,
                 program: "CLoopProgram") -> dict:
    """Per path, the function that runs round ``i``'s share and returns (wall, CPU) seconds per
    step: ``compiled_run`` whole records (at least ``steps`` steps), ``numpy_reference`` and
    ``filterpy`` ``reference_steps / ROUNDS`` steps each (one filter of each goes on along the
    record from round to round), ``c_loop_process`` ``steps`` steps of the C program."""
    share = max(1, reference_steps // ROUNDS)
    shares = {"compiled_run": compiled_run_share(model, family, work, steps),
              "numpy_reference": stepping_share(reference_stepper(family, work), work, share)}
    stepper = filterpy_stepper(model, family, work)
    if stepper is not None:
        shares["filterpy"] = stepping_share(stepper, work, share)
    shares["c_loop_process"] = lambda i: program.run(family)
    return shares


class CLoopProgram:
    """``c_loop_process``: :data:`C_LOOP` as a program of its own (the harness ``--instructions``
    counts) over ``steps`` steps; its wall and CPU times per step are measured by the program."""

    def __init__(self, exe: Path, stdin: str, steps: int):
        self.exe, self.stdin, self.steps = exe, stdin, steps

    def run(self, family: str) -> tuple[float, float]:
        """(wall, CPU) seconds per step: medians over the program's batches of 100 steps."""
        proc = subprocess.run([str(self.exe), family, str(self.steps)], input=self.stdin, capture_output=True,
                              text=True, check=True)
        wall, code, cpu = proc.stdout.split()
        if int(code):
            raise RuntimeError(f"c_loop: {family} step returned a failure code")
        return 1e-6 * float(wall), 1e-6 * float(cpu)


def _compile_c_loop(directory: Path, tmp: Path, defines: tuple[str, ...] = ()) -> Path:
    """:data:`C_LOOP` compiled against the bundle in ``directory`` with its flags, in ``tmp``."""
    tmp.mkdir(parents=True, exist_ok=True)
    return callgrind.compile_driver(directory, callgrind.driver_source(__package__, C_LOOP), tmp / "c_loop",
                                    defines=("-D_POSIX_C_SOURCE=199309L", *defines))


def time_compiled_step(model, family: str, work: Workload, batch: int = 100, steps: int | None = None,
                       c_loop: "CLoop | None" = None) -> dict[str, timing.Samples]:
    """Seconds per ``step`` call of each batch: ``compiled_step`` and ``compiled_step_rows`` (C
    fast path, inputs ready or indexed in the loop) and ``compiled_step_python`` (the Python
    contract path), each on its own filter over the same ``steps`` (default ``work.steps``), in
    alternate batches; with ``c_loop``, also the C loop's batches over the same steps, in turn
    with them."""
    paths = ("compiled_step", "compiled_step_rows", "compiled_step_python")
    filters = {path: model.filter(family, work.x0, work.P0, TUNING["Q"], t0=work.base_times[0], **_options(family))
               for path in paths}
    filters["compiled_step_python"].fast_path = False
    if c_loop is not None:
        filters["c_loop"] = c_loop
    times, z, q, dt = work.base_times, work.z, work.q, 1.0 / RATE_HZ
    ready = [(float(times[i - 1]), z[i].copy(), q[i].copy()) for i in range(len(times))]

    def batch_of(path: str, f):
        """Batch ``b`` of ``path``: steps b * batch .. (b + 1) * batch - 1."""
        if path == "c_loop":
            return lambda b: f.batch(family, b * batch, batch)
        if path == "compiled_step_rows":
            def rows(b):
                for k in range(b * batch, (b + 1) * batch):
                    i = work.index(k)
                    if i == 1:                  # the segment starts again (one batch's median is spared)
                        f.x, f.P, f.t = work.x0, work.P0, times[0]
                    f.step(times[i - 1], dt, z[i], "radar", q=q[i])
            return rows

        def prepared(b):
            for k in range(b * batch, (b + 1) * batch):
                i = work.index(k)
                if i == 1:
                    f.x, f.P, f.t = work.x0, work.P0, times[0]
                t, z_i, q_i = ready[i]
                f.step(t, dt, z_i, "radar", q=q_i)
        return prepared

    batches = -(-(work.steps if steps is None else steps) // batch)
    return timing.interleaved({path: batch_of(path, f) for path, f in filters.items()}, batches, calls=batch)



class CLoop:
    """``c_loop`` in this process: the C of :data:`C_LOOP_BATCH` compiled against the bundle in
    ``directory`` with its flags (the library the filters run) and called through ctypes once per
    batch of steps (one ctypes call per 100 steps: ~0.01 µs a step), so its batches alternate with
    the Python paths' under the same load and cache. Each filter carries its own x, P."""

    def __init__(self, work: Workload, directory: Path, tmp: Path):
        library = callgrind.compile_driver(directory, callgrind.driver_source(__package__, C_LOOP_BATCH),
                                           tmp / "c_loop_batch.so", defines=("-shared", "-fPIC"))
        self.function = ctypes.CDLL(str(library)).c_loop_batch
        self.function.restype = ctypes.c_int
        self.function.argtypes = [ctypes.c_int] * 4 + [ctypes.c_void_p] * 10 + [ctypes.c_double] * 2
        p = np.array([L.GUIDANCE[name] for name in L.GUIDANCE_PARAMS])
        self.constants = [np.ascontiguousarray(a, dtype=float) for a in (
            work.base_times, work.z, work.q, work.x0, np.ravel(work.P0, "F"))]
        self.state = {family: (np.array(work.x0, dtype=float), np.ravel(work.P0, "F").copy()) for family in FILTERS}
        self.parameters = [np.ascontiguousarray(a, dtype=float) for a in (
            p, np.ravel(TUNING["Q"], "F"), np.ravel(np.diag(np.square(L.RADAR_SIGMA)), "F"))]
        self.n = len(work.base_times)

    def batch(self, family: str, k0: int, count: int) -> None:
        x, P = self.state[family]
        pointers = [a.ctypes.data for a in self.constants + [x, P] + self.parameters]
        code = self.function(int(family == "ukf"), k0, count, self.n, *pointers, TUNING["kappa"], 1.0 / RATE_HZ)
        if code:
            raise RuntimeError(f"c_loop: {family} step returned a failure code")


def compiled_run_share(model, family: str, work: Workload, steps: int):
    """Round ``i``'s share of ``compiled_run``: whole records through one ``run`` call each (as
    many as make ``steps`` steps, at least one), (wall, CPU) seconds per step."""
    f = model.filter(family, work.x0, work.P0, TUNING["Q"], t0=work.base_times[0], **_options(family))
    n = len(work.base_times)
    records = max(1, int(np.ceil(steps / n)))

    def whole_records():
        for _ in range(records):
            f.x, f.P, f.t = work.x0, work.P0, work.base_times[0]
            f.run(work.base_times, work.z, "radar", q=work.q)
    return lambda i: per_step(timing.timed(whole_records), records * n)


def stepping_share(step, work: Workload, steps: int):
    """Round ``i``'s share of a filter stepped from Python, ``step(t_previous, dt, z, q)``: steps
    ``i * steps`` to ``(i + 1) * steps - 1`` of the record (repeated), (wall, CPU) s per step."""
    def share(i):
        def steps_of():
            for k in range(i * steps, (i + 1) * steps):
                j = work.index(k)
                step(work.base_times[j - 1], 1.0 / RATE_HZ, work.z[j], work.q[j])
        return per_step(timing.timed(steps_of), steps)
    return share


def per_step(timed: tuple, steps: int) -> tuple[float, float]:
    """(wall, CPU) seconds per step from :func:`timing.timed`'s (result, wall, CPU) over ``steps``."""
    _, wall, cpu = timed
    return wall / steps, cpu / steps


def reference_stepper(family: str, work: Workload):
    ref = ReferenceFilter("launcher", family, work.x0, work.P0, TUNING["Q"], kappa=TUNING["kappa"])
    return lambda t, dt, z, q: ref.step(t, dt, z, "radar", q)


#: Parts of a step counted by ``--instructions``: the predict and update calls on their own,
#: the fused step call, and a step inside the compiled run loop.
PARTS = ("predict", "update", "step", "run", "backward")
#: Exclusive instructions per call of the functions around the kernels (rows of the parts table):
#: ``wrapper``, the public step function's own work (input checks, z masking, argument set-up,
#: output checks and copies); ``composition``, a fused-step kernel's own work (its copies and
#: selections; 0 while the C API calls predict and update itself); ``loop``,
#: the run loop's own work per step (its per-step checks, the state history).
SELF_COSTS = {"wrapper": ("step", ("{m}_{f}_step_radar", "{m}_{f}_step_radar_eval")),
              "composition": ("step", ("{m}_k_{f}_step_radar", "{m}_k_{f}_step_radar_casadi_copy")),
              "loop": ("run", ("{m}_{f}_step_radar_run",))}


#: Where the fused step's instructions go (rows of the parts table): exclusive counts of
#: the functions of one ``step`` call, grouped by a test on the function's name (``m`` the model,
#: ``f`` the filter): the propagation (f_d and F, or f_d at the sigma points, with their event
#: dispatchers and SIMD lanes; libmvec's vector sin/cos count as libm), the measurement function (h and H; the UKF's h at its sigma points, in lanes too), the
#: predict and update kernels' own work, and the C math library (sincos, atan2, exp, ...).
STEP_FUNCTIONS = {
    "step: propagation": lambda name, m, f: (name.startswith((f"{m}_fn_", f"{m}_lanes_"))
                                             and not name.startswith((f"{m}_fn_h_", f"{m}_lanes_h_"))),
    "step: h and H": lambda name, m, f: name.startswith((f"{m}_fn_h_", f"{m}_lanes_h_")),
    "step: predict kernel": lambda name, m, f: name.startswith(f"{m}_k_{f}_predict"),
    "step: update kernel": lambda name, m, f: name.startswith(f"{m}_k_{f}_update_"),
    "step: libm": lambda name, m, f: not name.startswith(f"{m}_") and name != "main",
}


def step_breakdown(counts: dict[str, float], model: str, family: str) -> dict[str, float]:
    """:data:`STEP_FUNCTIONS`'s rows from the exclusive counts per function of a ``step`` call."""
    return {row: sum(n for name, n in counts.items() if test(name, model, family))
            for row, test in STEP_FUNCTIONS.items()}


def c_loop_instructions(work: Workload) -> dict[str, dict]:
    """Instructions per call of each part of both filters' step, counted under callgrind
    (deterministic, unlike wall-clock time on a shared machine) with the C loop compiled against
    build/launcher/ with the library's flags; {} per filter without valgrind."""
    directory = build_model("launcher").directory
    out = {family: {} for family in FILTERS}
    if not shutil.which("valgrind"):
        return out
    with tempfile.TemporaryDirectory() as tmp:
        exe = _compile_c_loop(directory, Path(tmp))
        lockstep_exes = {suffix: _compile_c_loop(build_model("launcher", **build).directory,
                                                 Path(tmp) / f"lockstep{suffix}", ("-DSYMKF_LOCKSTEP",))
                         for suffix, build in (("", LOCKSTEP_BUILD), ("_exact", EXACT_LOCKSTEP_BUILD))}
        stdin = _c_loop_input(work)
        for family in FILTERS:
            counts = {part: _instructions_per_step(exe, family, part, stdin, Path(tmp)) for part in PARTS}
            parts = {part: total for part, (total, _) in counts.items()}
            parts["backward"] -= parts["run"]          # the driver's backward part runs the forward loop first
            for row, (part, functions) in SELF_COSTS.items():
                parts[row] = sum(counts[part][1].get(f.format(m="launcher", f=family), 0) for f in functions)
            parts.update(step_breakdown(counts["step"][1], "launcher", family))
            for suffix, lockstep_exe in lockstep_exes.items():
                lockstep, _ = _instructions_per_step(lockstep_exe, family, "lockstep", stdin, Path(tmp))
                both, _ = _instructions_per_step(lockstep_exe, family, "smooth-lockstep", stdin, Path(tmp))
                parts[f"lockstep{suffix}"] = (lockstep - parts["run"]) / LOCKSTEP_RUNS   # per run-step of 4 runs
                parts[f"backward_lockstep{suffix}"] = (both - lockstep) / LOCKSTEP_RUNS
            out[family] = {"instructions_per_step": parts["step"], "instructions_by_part": parts}
    return out


#: The build of the "scalar" row of ``--instructions``: the UKF's sigma points one at a time
#: (scalar libm), as the flight bundle computes them.
LANES_BUILD = {"ukf_lanes": True}


def lanes_step_instructions(work: Workload) -> dict[str, float]:
    """Instructions per fused UKF step of :data:`LANES_BUILD` (the EKF's step has no lanes)."""
    if not shutil.which("valgrind"):
        return {}
    with tempfile.TemporaryDirectory() as tmp:
        exe = _compile_c_loop(build_model("launcher", **LANES_BUILD).directory, Path(tmp))
        return {"ukf": _instructions_per_step(exe, "ukf", "step", _c_loop_input(work), Path(tmp))[0]}


def _c_loop_input(work: Workload) -> str:
    Q, R = TUNING["Q"], np.diag(np.square(L.RADAR_SIGMA))
    p = [L.GUIDANCE[name] for name in L.GUIDANCE_PARAMS]
    head = np.concatenate([work.x0, work.P0.ravel("F"), Q.ravel("F"), R.ravel("F"), [TUNING["kappa"]], p])
    lines = [" ".join(f"{v:.17g}" for v in head), str(len(work.base_times))]
    lines += [" ".join(f"{v:.17g}" for v in np.concatenate([[t], z, q]))
              for t, z, q in zip(work.base_times, work.z, work.q)]
    return "\n".join(lines)


def _instructions_per_step(exe: Path, family: str, part: str, stdin: str, tmp: Path) -> tuple[float, dict]:
    """Callgrind's instruction count of 1100 calls (steps) of ``part`` minus that of 100, per call
    (the first 55 s of the flight at 20 Hz, no event inside: event steps are 4 in a flight), and
    the same difference of each function's exclusive count (``callgrind_annotate``), per call."""
    def count(steps: int) -> tuple[int, dict]:
        out = tmp / f"callgrind.{steps}.out"
        total, stdout = callgrind.run([str(exe), family, str(steps), part], stdin, out)
        if int(stdout.split()[1]):
            raise RuntimeError(f"c_loop: {family} {part} returned a failure code")
        return total, callgrind.function_counts(out) if shutil.which("callgrind_annotate") else {}
    (many, by_many), (few, by_few) = count(1100), count(100)
    return (many - few) / 1000, {name: (n - by_few.get(name, 0)) / 1000 for name, n in by_many.items()}


def filterpy_stepper(model, family: str, work: Workload):
    """FilterPy's own EKF/UKF step on our compiled model functions (None if FilterPy is absent)."""
    try:
        from .filterpy_adapter import make_filterpy_filter
    except ImportError:
        return None
    return make_filterpy_filter(model, family, work.x0, work.P0, TUNING["Q"], TUNING["kappa"])


def measure(steps: int, reference_steps: int, campaign: bool, instructions: bool = False,
            scheduler: str | None = None) -> dict:
    load_before = timing.load_average()
    model = load("launcher", backend="compiled")
    work = Workload(steps)
    c_loop = c_loop_instructions(work) if instructions else {family: {} for family in FILTERS}
    samples, spread = time_paths(model, work, reference_steps)
    rows = []
    for family in FILTERS:
        for path in PATHS:
            if path not in samples[family]:
                continue
            row = {"filter": family, "path": path, "us_per_step": samples[family][path].us,
                   "cpu_us_per_step": samples[family][path].cpu_us}
            if path == "c_loop" and "instructions_per_step" in c_loop[family]:
                row["instructions_per_step"] = c_loop[family]["instructions_per_step"]
                row["instructions_by_part"] = c_loop[family]["instructions_by_part"]
            rows.append(row)
    report = {"rows": rows, "paper_ms_per_step": L.PAPER_MS_PER_STEP, "ratios": ratios(rows),
              "ratios by round": spread, "steps": steps, "reference_steps": reference_steps, "rounds": ROUNDS,
              "load_average": {"before": load_before, "after": timing.load_average()}}
    if instructions:
        report["lanes_instructions_per_step"] = lanes_step_instructions(work)
    if campaign:
        report.update(time_campaign(scheduler))
    return report


#: The rows' order (the table's): slowest first.
PATHS = ("numpy_reference", "filterpy", "compiled_step_python", "compiled_step_rows", "compiled_step", "compiled_run",
         "c_loop", "c_loop_process")


def time_campaign(scheduler: str | None = None, runs: int = 100) -> dict:
    """Wall and CPU time of the default campaign (4 cases x ``runs`` x both filters), its
    throughput per worker (runs/s of wall time divided by the workers), where the CPU went, and
    which build it ran. ``campaign_cpu_s`` is the CPU of this process and of the worker
    processes the campaign started (a LocalCluster's; all the work either way); the tasks' own CPU (``campaign_task_cpu_s``, measured where they run) splits into the compiled
    runs of each filter (``campaign_run_cpu_s``) and the rest (the truth, once per process and
    rate; radar draws, filter set-up, errors, NEES, per-run rows)."""
    start = time.perf_counter()
    campaign = Campaign(runs, 2005, scheduler=scheduler)
    results = campaign.run()
    wall = time.perf_counter() - start
    task_cpu = sum(r.task_cpu_s for r in results)
    run_cpu = {f: sum(r.cpu_s[f] for r in results) for f in FILTERS}
    return {"campaign_runs": runs, "campaign_wall_s": wall, "campaign_cpu_s": campaign.stats.cpu_s,
            "campaign_task_cpu_s": task_cpu, "campaign_run_cpu_s": run_cpu,
            "campaign_other_task_cpu_s": task_cpu - sum(run_cpu.values()),
            "campaign_build": campaign_build(campaign),
            "campaign_executor": campaign.stats.executor, "campaign_workers": campaign.stats.workers,
            "campaign_runs_per_s_per_worker": campaign.stats.runs / wall / campaign.stats.workers}


def campaign_build(campaign: Campaign) -> dict:
    """The library a campaign ran: content hash, -O flags (and the units compiled otherwise)."""
    manifest = getattr(compiled_model(campaign.model_key).backend, "manifest", None) or {}
    return {"content_hash": campaign.model_key.content_hash[:12], "optimization": manifest.get("optimization"),
            "unit_optimization": sorted(set((manifest.get("unit_optimization") or {}).values()))}


def campaign_lines(report: dict) -> list[str]:
    """The campaign's wall and CPU seconds, where the CPU went, and the build it ran."""
    runs, build = report["campaign_run_cpu_s"], report["campaign_build"]
    units = f", some units {'/'.join(build['unit_optimization'])}" if build["unit_optimization"] else ""
    return [f"campaign (4 cases x {report['campaign_runs']} runs x 2 filters): {report['campaign_wall_s']:.1f} s wall, "
            f"{report['campaign_cpu_s']:.1f} s CPU (here and in its worker processes), {report['campaign_executor']}, "
            f"{report['campaign_runs_per_s_per_worker']:.1f} runs/s per worker",
            f"  CPU in the tasks {report['campaign_task_cpu_s']:.1f} s: compiled runs EKF {runs['ekf']:.1f} s + "
            f"UKF {runs['ukf']:.1f} s, the rest (truth, draws, metrics) {report['campaign_other_task_cpu_s']:.1f} s; "
            f"library {build['content_hash']} ({build['optimization']}{units})"]


#: The lockstep rows of the parts table: the campaign's build (libmvec in the prediction) and the
#: exact one (libm lane by lane: Filter.run's numbers bit for bit).
LOCKSTEP_ROWS = {"lockstep": "run-step in lockstep", "backward_lockstep": "backward step, lockstep",
                 "lockstep_exact": "  the same, exact (libm)", "backward_lockstep_exact": "  backward, exact (libm)"}


def instruction_parts_table(report: dict) -> list[str]:
    """Instructions per call of each part (predict, update, fused step, a step inside the run
    loop), of the code around the kernels (SELF_COSTS) and of the step's functions (STEP_FUNCTIONS)."""
    parts = {r["filter"]: r["instructions_by_part"] for r in report["rows"] if "instructions_by_part" in r}
    if not parts:
        return []
    lines = ["", f"{'instructions per call':<26}" + "".join(f"{f.upper():>13}" for f in FILTERS)]
    for part in (*PARTS, *LOCKSTEP_ROWS, *SELF_COSTS, *STEP_FUNCTIONS):
        label = {"wrapper": "step: wrapper, checks", "composition": "step: composition",
                 "loop": "run: loop, checks", "backward": "smoother: backward step",
                 **LOCKSTEP_ROWS}.get(part, part)
        lines.append(f"{label:<26}" + "".join(f"{parts[f][part]:>13,.0f}" if part in parts[f] else f"{'-':>13}"
                                              for f in FILTERS))
    return lines


def ratios(rows: list[dict]) -> dict:
    value = {(r["filter"], r["path"]): r["us_per_step"] for r in rows}
    out = {}
    for family in FILTERS:
        step = value[(family, "compiled_step")]
        out[family] = {"numpy_reference/compiled_step": value[(family, "numpy_reference")] / step,
                       "compiled_step/c_loop": step / value[(family, "c_loop")],
                       "compiled_step/c_loop_process": step / value[(family, "c_loop_process")],
                       "compiled_step_rows/c_loop": value[(family, "compiled_step_rows")] / value[(family, "c_loop")],
                       "compiled_step_python/c_loop": value[(family, "compiled_step_python")] / value[(family, "c_loop")],
                       "compiled_run/c_loop": value[(family, "compiled_run")] / value[(family, "c_loop")]}
        if (family, "filterpy") in value:
            out[family]["filterpy/compiled_step"] = value[(family, "filterpy")] / step
    paths = sorted({r["path"] for r in rows})
    out["ukf/ekf"] = {path: value[("ukf", path)] / value[("ekf", path)] for path in paths
                      if ("ukf", path) in value and ("ekf", path) in value}
    return out


def human_table(report: dict) -> str:
    value = {(r["filter"], r["path"]): r["us_per_step"] for r in report["rows"]}
    cpu = {(r["filter"], r["path"]): r["cpu_us_per_step"] for r in report["rows"]}
    paths = [p for p in PATHS if ("ekf", p) in value]
    load = report["load_average"]
    lines = [f"medians of {report['rounds']} interleaved rounds; wall and this thread's CPU µs per step; "
             f"load average {load['before'][0]:.2f} before, {load['after'][0]:.2f} after (1 min; "
             f"{load['after'][1]:.2f} over 5 min) on {os.cpu_count()} cores",
             f"{'path':<21}{'EKF us/step':>12}{'(CPU)':>9}{'UKF us/step':>13}{'(CPU)':>9}{'UKF/EKF':>9}",
             f"{'paper (MATLAB)':<21}{report['paper_ms_per_step']['ekf'] * 1e3:>12.1f}{'':>9}"
             f"{report['paper_ms_per_step']['ukf'] * 1e3:>13.1f}{'':>9}"
             f"{report['paper_ms_per_step']['ukf'] / report['paper_ms_per_step']['ekf']:>9.2f}"]
    for path in paths:
        e, u = value[("ekf", path)], value[("ukf", path)]
        lines.append(f"{path:<21}{e:>12.2f}{cpu[('ekf', path)]:>9.2f}{u:>13.2f}{cpu[('ukf', path)]:>9.2f}{u / e:>9.2f}")
    counts = {r["filter"]: r["instructions_per_step"] for r in report["rows"] if "instructions_per_step" in r}
    if counts:
        lines.append(f"{'c_loop instr.':<18}{counts['ekf']:>14.0f}{counts['ukf']:>14.0f}{counts['ukf'] / counts['ekf']:>10.2f}")
        lanes = report.get("lanes_instructions_per_step", {}).get("ukf")
        if lanes:           # the same step with four sigma points at a time (ukf_lanes=True)
            lines.append(f"{'  SIMD lanes':<18}{counts['ekf']:>14.0f}{lanes:>14.0f}{lanes / counts['ekf']:>10.2f}")
    for family in FILTERS:
        lines.append(f"{family}: " + ", ".join(f"{k} = {v:.1f}" for k, v in report["ratios"][family].items()))
    for name, by_round in report.get("ratios by round", {}).items():
        family, ratio = name.split()
        lines.append(f"{family}: {ratio} = {report['ratios'][family][ratio]:.2f} (medians over {len(by_round)} rounds; "
                     f"each round's: {min(by_round):.2f}-{max(by_round):.2f})")
    if "campaign_wall_s" in report:
        lines += campaign_lines(report)
    lines += instruction_parts_table(report)
    return "\n".join(lines)
