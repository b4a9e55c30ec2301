"""Launcher EKF/UKF masks: a masked component contributes nothing, nan="mask" equals an explicit mask."""
import numpy as np
import pytest

from symkf.models import launcher as L
from symkf.runtime import SymkfError

X0 = L.initial_state() + np.array([5.0, 0, 0, 500.0, 0, 0])
P0 = np.diag([10.0, 1e-4, 1e-4, 1e3, 1e-5, 1e-5]) ** 2
Q = np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14])
STATION = L.station_params(1)
Z = np.array([60.0, 1.2, 2.5])


@pytest.fixture(params=["ekf", "ukf"])
def filt(request, launcher_compiled):
    f = launcher_compiled.filter(request.param, X0, P0, Q)
    f.predict(0.0, 0.05)
    return f


def _unchanged(f, x, P):
    np.testing.assert_array_equal(f.x, x)
    np.testing.assert_array_equal(f.P, P)


def test_nan_measurement_masked_on_request_equals_explicit_mask(launcher_compiled, filt):
    twin = launcher_compiled.filter(filt.family, filt.x, filt.P, Q)
    filt.update([60.0, np.nan, 2.5], "radar", q=STATION, nan="mask")
    twin.update([60.0, 0.0, 2.5], "radar", q=STATION, mask=[1, 0, 1])
    np.testing.assert_array_equal(filt.x, twin.x)
    assert filt.y("radar")[1] == 0.0


def test_masked_component_contributes_nothing(launcher_compiled, filt):
    twin = launcher_compiled.filter(filt.family, filt.x, filt.P, Q)
    filt.update([60.0, 1.2, 2.5], "radar", q=STATION, mask=[1, 1, 0])
    twin.update([60.0, 1.2, -1e9], "radar", q=STATION, mask=[1, 1, 0])
    np.testing.assert_array_equal(filt.x, twin.x)
    np.testing.assert_array_equal(filt.P, twin.P)


def test_all_masked_update_is_a_no_op(filt):
    x, P = filt.x.copy(), filt.P.copy()
    filt.update([np.nan, np.nan, np.nan], "radar", q=STATION, mask=[0, 0, 0])
    _unchanged(filt, x, P)


def test_ukf_rejects_nonpositive_scaling(launcher_compiled):
    f = launcher_compiled.ukf(X0, P0, Q, kappa=-6.0)
    with pytest.raises(SymkfError, match="SYMKF_ERR_DOMAIN|SYMKF_ERR_NOT_PD"):
        f.predict(0.0, 0.05)
    np.testing.assert_array_equal(f.x, X0)
