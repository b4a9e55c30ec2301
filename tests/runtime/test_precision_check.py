"""runtime/precision.py: a float state whose spacing exceeds the filter's own 1-sigma is named,
with the numbers; one that float resolves is not."""
import numpy as np

from symkf.runtime.precision import SPACING_FRACTION, check, sigmas


def test_a_geocentric_radius_with_a_sub_metre_sigma_is_reported():
    x = np.array([[6.4e6, 100.0], [6.663e6, 120.0]])          # r (m), an altitude-like state (m)
    sigma = np.array([[10.0, 1.0], [0.3, 0.3]])
    found = check(["r", "h"], x, sigma)
    assert [f.state for f in found] == ["r"]
    assert found[0].step == 1 and found[0].spacing == 0.5 and found[0].sigma == 0.3
    assert "float spacing 0.5 against a 1-sigma of 0.3" in str(found[0])


def test_scale_converts_to_the_state_unit_and_sigmas_from_factors():
    L = np.array([[[2.0, 0.0], [1.0, 1.0]]])
    assert np.allclose(sigmas(L, factor=True), [[2.0, np.sqrt(2.0)]])
    assert np.allclose(sigmas(L @ L.transpose(0, 2, 1), factor=False), [[2.0, np.sqrt(2.0)]])
    x = np.array([[1.0e6, 1.0]])
    spacing = float(np.spacing(np.float32(1.0e6)))
    found = check(["a", "b"], x, np.array([[spacing / SPACING_FRACTION / 2, 1.0]]), scale=np.array([4.0, 1.0]))
    assert [f.state for f in found] == ["a"] and found[0].spacing == 4 * spacing
