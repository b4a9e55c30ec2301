"""Property: for every filter under the contract (tests/contract_cases/), any step either raises
with x, P and t bit-identical, or returns OK (0 or SYMKF_GATED) with a finite state, P symmetric
positive semi-definite and every declared quaternion of unit norm. Hypothesis draws the step
length (including 0, NaN, Inf, huge), the measurement (scaled, shifted, NaN, huge), the mask and
the initial covariance's scale."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from contract_cases import all_cases
from symkf.runtime import SymkfError, load

CASES = all_cases()
MODELS = tuple(dict.fromkeys(case.model for case in CASES))
awkward = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, 1e-300, 1e300, -1.0, 1e-3]))


@pytest.fixture(scope="module")
def compiled():
    return {name: load(name, backend="compiled") for name in MODELS}


def _psd(P: np.ndarray) -> bool:
    scale = max(float(np.max(np.abs(P))), 1e-300)
    return bool(np.isfinite(P).all() and np.array_equal(P, P.T) and np.linalg.eigvalsh(P)[0] >= -1e-8 * scale)


def _unit_quaternions(f) -> bool:
    return all(abs(np.linalg.norm(f.x[q["states"]]) - 1) < 1e-9 for q in f.model.get("quaternions", []))


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dt=awkward, gain=awkward, offset=st.floats(-1e6, 1e6), used=st.lists(st.sampled_from([0.0, 1.0]), min_size=8, max_size=8),
       scale=st.floats(1e-6, 1e6))
# a step of 7913 s (the launcher's prediction explodes to P ~ 1e247) with one component used: the
# update's round-off once left finite negative variances, returned as a success
@example(dt=7913.0, gain=0.0, offset=0.0, used=[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0], scale=1.0)
def test_a_step_errs_cleanly_or_keeps_a_valid_state(compiled, case, dt, gain, offset, used, scale):
    f = case.make(compiled[case.model], P_scale=scale)
    a = case.inputs(1)
    z = np.asarray(a["z"], dtype=float) * gain + offset
    mask = np.array(used[:case.mask_length()])
    before = (f.x.copy(), None if "P" not in f._buffers else f.P.copy(), f.t)
    try:
        code = f.step(f.t, dt, z, case.measurement, q=a["q"], mask=mask, u=a["u"])
    except (ValueError, SymkfError):
        assert np.array_equal(f.x, before[0]) and f.t == before[2]
        assert before[1] is None or np.array_equal(f.P, before[1])
        return
    assert code in (0, 6)
    assert np.isfinite(f.x).all() and _unit_quaternions(f)
    if before[1] is not None:
        assert _psd(np.asarray(f.P))
