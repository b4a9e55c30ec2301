"""NIS from run() (the generated ``_run_diag`` loop, runtime/innovations.py) equals the step
loop's y^T S^-1 y, with masks, gates and failed steps; and the consistency helper's averages and
chi-square bands (scenarios/consistency.py)."""
import numpy as np
import pytest
from scipy.stats import chi2

from symkf.codegen.spec import STATUS_GATED
from symkf.scenarios.consistency import chi2_band, monte_carlo_average, nees_series, time_average
from symkf.scenarios.launcher.truth import propagate, radar_track

P0 = np.diag([10.0, 1e-4, 1e-4, 1000.0, 1e-5, 1e-5]) ** 2
Q = np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14])


@pytest.fixture(scope="module")
def flight():
    times = np.arange(121) * 0.05
    truth = propagate(times)
    track = radar_track(times, truth)
    return times, truth, track.noisy(np.random.default_rng(7)), track.station_params()


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_run_nis_equals_the_step_loop(launcher_compiled, flight, family):
    times, truth, z, q = flight
    x0 = truth[0] + np.array([10.0, 1e-8, 1e-8, 1000.0, 1e-8, 1e-8])
    mask = np.ones_like(z)
    mask[30:40, 1] = 0.0                       # elevation missing: 2 components used
    mask[50] = 0.0                             # nothing used
    z = z.copy()
    z[70, 0] += 500.0                          # an outlier the gate refuses
    run_filter = launcher_compiled.filter(family, x0, P0, Q)
    step_filter = launcher_compiled.filter(family, x0, P0, Q)
    for f in (run_filter, step_filter):
        f.set_gate("radar", probability=0.9999)
    result = run_filter.run(times, z, "radar", q=q, mask=mask)
    assert result.status[70] == STATUS_GATED
    expected = []
    step_filter.t = times[0]
    step_filter.update(z[0], "radar", q=q[0], mask=mask[0])            # a run's first step: dt = 0
    expected.append(step_filter.y("radar") @ np.linalg.solve(step_filter.S("radar"), step_filter.y("radar")))
    for k in range(1, len(times)):
        step_filter.step(times[k - 1], times[k] - times[k - 1], z[k], "radar", q=q[k], mask=mask[k])
        sigma = np.sqrt(np.diag(step_filter.S("radar")))      # in units of the innovation's sigma
        np.testing.assert_allclose(result.y[k] / sigma, step_filter.y("radar") / sigma, rtol=0, atol=1e-9)
        np.testing.assert_allclose(result.S[k] / np.outer(sigma, sigma), step_filter.S("radar") / np.outer(sigma, sigma),
                                   rtol=0, atol=1e-9)
        expected.append(step_filter.y("radar") @ np.linalg.solve(step_filter.S("radar"), step_filter.y("radar")))
    np.testing.assert_allclose(result.nis, expected, rtol=1e-8, atol=1e-10)
    assert result.nis_dof[35] == 2 and result.nis_dof[50] == 0 and result.nis_dof[60] == 3
    assert result.nis[50] == 0.0 and result.nis[70] > chi2.ppf(0.9999, 3)


def test_a_nan_masked_component_does_not_count(launcher_compiled, flight):
    times, truth, z, q = flight
    f = launcher_compiled.ekf(truth[0], P0, Q)
    z = z.copy()
    z[40, 0] = np.nan                       # masked by the NaN policy: no update, not a failure
    result = f.run(times, z, "radar", q=q, nan="mask")
    assert result.nis_dof[40] == 2 and np.isfinite(result.nis).all()


def test_chi2_band_and_averages():
    low, high = chi2_band(3 * 50, 50)
    assert low < 3 < high and np.isclose(low, chi2.ppf(0.025, 150) / 50)
    rng = np.random.default_rng(3)
    values = rng.chisquare(3, (200, 400))          # 200 runs of a consistent 3-dof series
    mc = monte_carlo_average(values, 3)
    assert mc.value.shape == (400,) and 0.9 < np.mean(mc.inside) <= 1.0
    assert np.allclose(mc.expected, 3)
    inside = [time_average(run, np.full(400, 3)).inside for run in values]
    assert 0.9 < np.mean(inside) < 0.99                 # a 95 % band
    assert np.isclose(time_average(values[0], 3).expected, 3)
    inflated = time_average(values[0] * 2, 3)       # an overconfident filter leaves the band
    assert not inflated.inside
    gaps = values[:2].copy()
    gaps[0, :10] = np.nan                           # steps without a value are left out
    mixed = monte_carlo_average(gaps, np.array([[3] * 400, [0] * 5 + [3] * 395]))
    assert np.isnan(mixed.value[:5]).all()
    np.testing.assert_allclose(mixed.value[5:10], gaps[1, 5:10])
    assert mixed.value[20] == pytest.approx(gaps[:, 20].mean())


def test_nees_series_of_a_consistent_run():
    rng = np.random.default_rng(5)
    P = np.array([[4.0, 1.0], [1.0, 2.0]])
    errors = rng.multivariate_normal([0, 0], P, size=2000)
    series = nees_series(errors, np.zeros_like(errors), np.broadcast_to(P, (2000, 2, 2)))
    np.testing.assert_allclose(series, np.einsum("ki,ij,kj->k", errors, np.linalg.inv(P), errors))
    assert time_average(series, 2).inside
