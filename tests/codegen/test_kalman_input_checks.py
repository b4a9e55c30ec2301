"""Issue 12: the EKF/UKF kernels test no input for NaN/Inf except an update's x and P (every caller
tests the inputs first: the C wrappers, the run loops and the VM backend); a fused step's
predicted x and P reach the update unchecked by any caller, so the update tests those."""
import numpy as np
import pytest

from symkf.codegen.spec import STATUS_NONFINITE
from symkf.models import launcher as L

X = np.array([1500.0, 0.9, -1.4, 6.4e6, 2.22, 0.6])
P = np.diag([1.0, 1e-8, 1e-8, 100.0, 1e-12, 1e-12])


def _kernel(bundle, name):
    return next(k.function for k in bundle.kernels if k.name == name)


def _update_args(P_in, kappa=None):
    args = [60.0, X, P_in, np.zeros(0), np.array([L.GUIDANCE[n] for n in L.GUIDANCE_PARAMS]), L.station_params(1),
            np.array([1e5, 0.3, 3.0]), np.ones(3), np.diag(np.square(L.RADAR_SIGMA)), np.zeros(3)]
    return args + ([kappa] if kappa is not None else [])


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_update_kernel_reports_a_non_finite_predicted_state(launcher_bundle, family):
    update = _kernel(launcher_bundle, f"{family}_update_radar")
    kappa = 0.0 if family == "ukf" else None
    assert int(update.call(_update_args(P, kappa))[-1]) == 0
    for bad in (np.inf, np.nan):
        for i, j in ((3, 3), (5, 0)):
            P_bad = P.copy()
            P_bad[i, j] = bad
            assert int(update.call(_update_args(P_bad, kappa))[-1]) == STATUS_NONFINITE
        x_bad = X.copy()
        x_bad[1] = bad
        args = _update_args(P, kappa)
        args[1] = x_bad
        assert int(update.call(args)[-1]) == STATUS_NONFINITE
