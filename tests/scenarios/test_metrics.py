"""The metrics' one angle-wrap helper and what depends on it (paper 004 eq (8), (11), NEES)."""
import numpy as np
import pytest

from symkf.scenarios.launcher import campaign as C
from symkf.scenarios.metrics import ErrorAccumulator, nees, state_error

ANGLES = np.array([False, True, True, False, True, True])


def test_state_error_wraps_angles_only():
    truth = np.array([[10.0, 0.1, -3.1, 7.0e6, 2 * np.pi, 0.0]])
    estimate = np.array([[10.5, 0.1 - 2 * np.pi, 3.1, 7.0e6 + 2 * np.pi, 0.0, 4 * np.pi + 0.2]])
    error = state_error(truth, estimate, ANGLES)
    np.testing.assert_allclose(error, [[-0.5, 0.0, 2 * np.pi - 6.2, -2 * np.pi, 0.0, -0.2]], atol=1e-12)


@pytest.mark.parametrize("offset", [np.pi, -np.pi, 3 * np.pi, np.pi + 1e-9, -np.pi - 1e-9])
def test_wrapped_error_lies_in_half_open_interval(offset):
    error = state_error(np.array([[offset]]), np.zeros((1, 1)), [True])[0, 0]
    assert -np.pi < error <= np.pi
    assert np.isclose(np.cos(error), np.cos(offset)) and np.isclose(np.sin(error), np.sin(offset), atol=1e-9)


def test_state_error_rejects_wrong_flag_count():
    with pytest.raises(ValueError, match="expected 6 flags"):
        state_error(np.zeros((2, 6)), np.zeros((2, 6)), [True, False])


def test_a_run_360_degrees_off_has_converged():
    """Issue 11: the 'diverged' 10 Hz large UKF run 49 ended exactly 360 deg off in gamma."""
    n = 100
    truth = np.zeros((n, 6))
    estimate = truth.copy()
    estimate[n // 3:, 1] = 2 * np.pi + 1e-5            # converged, one turn away
    error = state_error(truth, estimate, ANGLES)
    assert C.outcome(error) == "ok"
    assert C.outcome(truth - estimate) == "diverged"     # the unwrapped error misclassifies it
    accumulator = ErrorAccumulator(n, 6)
    P = np.tile(np.eye(6) * 1e-8, (n, 1, 1))
    accumulator.add(truth, estimate, P, angles=ANGLES)
    assert accumulator.rms()[-1, 1] == pytest.approx(1e-5, rel=1e-6)
    np.testing.assert_allclose(nees(error, P)[-1], 1e-10 / 1e-8, rtol=1e-6)
