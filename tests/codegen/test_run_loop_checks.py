"""A compiled run checks the inputs that do not change along it (parameters, noise, the initial
state) once and the per-step inputs (t, dt, z, mask, q) at each step, and calls a fused step's
predict and update kernels itself. Past the Python contract, its codes and histories
must be exactly those of the same steps called one by one through the C step function, refused
steps included."""
import numpy as np
import pytest

from kernel_calls import run_in_c, step_by_step
from symkf.models import launcher as L
from symkf.codegen.spec import STATUS_GATED, STATUS_NONFINITE

STEPS = 12


@pytest.fixture(scope="module")
def record():
    """A 20 Hz stretch of the flight from lift-off: times, radar data, stations, x0, P0."""
    from symkf.scenarios.launcher.bench import Workload
    return Workload(STEPS)


def inputs(record, family: str, bad: str) -> dict[str, np.ndarray]:
    """Every input of ``<family>_step_radar_run`` in Fortran order; ``bad`` puts a NaN in one."""
    k = np.arange(1, STEPS + 1)
    values = {"t": record.base_times[k - 1], "dt": np.diff(record.base_times[:STEPS + 1]), "x": record.x0,
              "P": record.P0, "u": np.zeros(0), "p": np.array([L.GUIDANCE[n] for n in L.GUIDANCE_PARAMS]),
              "Q": np.diag([1e-6, 1e-12, 1e-12, 1e-4, 1e-16, 1e-16]), "q": record.q[k], "z": record.z[k],
              "mask": np.ones((STEPS, 3)), "R": np.diag(np.square(L.RADAR_SIGMA)), "gate": np.zeros(3),
              "kappa": np.array(0.0)}
    values = {name: np.array(v, dtype=float) for name, v in values.items()}
    values["mask"][5, 1] = 0.0
    values["z"][5, 1] = np.nan                         # masked: a NaN there is no error
    if bad == "z":
        values["z"][7, 2] = np.nan                     # used: step 7 is refused, the run goes on
    elif bad == "mask":
        values["mask"][3, 0] = np.nan
    elif bad == "t":
        values["t"][9] = np.inf
    elif bad == "R":
        values["R"][1, 1] = np.nan                     # every step refused
    elif bad == "x":
        values["x"][2] = np.nan                        # every step refused, x stays x0
    return values


@pytest.mark.parametrize("bad", ["none", "z", "mask", "t", "R", "x"])
@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_run_equals_c_steps_one_by_one(launcher_compiled, record, family, bad):
    backend = launcher_compiled.backend
    kernel = f"{family}_step_radar"
    values = inputs(record, family, bad)
    code, status, x_hist, P_hist = run_in_c(backend, kernel, values, STEPS)
    codes, xs, Ps = step_by_step(backend, kernel, values, STEPS)
    assert status == codes
    assert code == next((c for c in codes if c not in (0, STATUS_GATED)), 0)
    assert np.array_equal(x_hist, xs, equal_nan=True) and np.array_equal(P_hist, Ps, equal_nan=True)
    refused = {"none": 0, "z": 1, "mask": 1, "t": 1, "R": STEPS, "x": STEPS}[bad]
    assert codes.count(STATUS_NONFINITE) == refused and codes.count(0) == STEPS - refused
    if refused < STEPS:
        assert not np.array_equal(xs[-1], values["x"])          # the filter moved
