"""A float build says at build time which declared states it will not resolve
(models/float_range.py, codegen/float_check.py).

The launcher (paper 004) with ranges of the size its float runs show (r from the Earth's radius to
300 km above it, resolved to 0.3 m; theta within 0.05 rad east of the launch site, to 2e-8 rad:
the after-run check measured spacing/sigma 1.5 and 3.8 there): without its declared offsets (scaling off) the float build names r and
theta, with the numbers; with them (the float default) and in double it names nothing. A model
without declared ranges is not checked; a bad declaration is refused. The warning comes from the
build itself (a small user model file, built)."""
from __future__ import annotations

import copy
import warnings

import pytest

from symkf.codegen import build_model, make_config
from symkf.codegen.float_check import FloatResolutionWarning, unresolved
from symkf.models import get_model
from symkf.models import launcher as L
from symkf.models.errors import ModelError
from symkf.models.float_range import declare_range


def launcher_with_ranges():
    model = copy.copy(get_model("launcher"))
    model.state_ranges = {}
    declare_range(model, "r", low=L.R_EARTH, high=L.R_EARTH + 300e3, sigma=0.3)
    declare_range(model, "theta", low=L.LAUNCH_LONGITUDE, high=L.LAUNCH_LONGITUDE + 0.05, sigma=2e-8)
    return model


def test_unscaled_float_names_the_states_it_cannot_resolve():
    model = launcher_with_ranges()
    found = unresolved(model, make_config(model, precision="float", scaling=False))
    assert found == ["state 'r': carried as 6.678e+06, float spacing 0.5 against a declared 1-sigma of 0.3 (ratio 1.7)",
                     "state 'theta': carried as 2.276, float spacing 2.38e-07 against a declared 1-sigma of 2e-08 "
                     "(ratio 12)"]


def test_declared_offsets_and_double_resolve():
    model = launcher_with_ranges()
    assert unresolved(model, make_config(model, precision="float")) == []          # scaled: offsets R_EARTH, ...
    assert unresolved(model, make_config(model)) == []                             # double
    assert unresolved(get_model("launcher"), make_config("launcher", precision="float", scaling=False)) == []


def test_bad_declarations_are_refused():
    model = launcher_with_ranges()
    with pytest.raises(ModelError, match="no state 'altitude'"):
        declare_range(model, "altitude", 0.0, 1.0, 1.0)
    with pytest.raises(ModelError, match="sigma finite and > 0"):
        declare_range(model, "r", 6.4e6, 6.5e6, 0.0)
    with pytest.raises(ModelError, match="low <= high"):
        declare_range(model, "r", 6.5e6, 6.4e6, 1.0)


def test_the_float_build_warns(tmp_path, write_model):
    path = write_model(tmp_path / "far_cart.py", name="far_cart")
    path.write_text(path.read_text().replace(
        "    return m\n", "    from symkf.models.float_range import declare_range\n"
                         "    declare_range(m, 'pos', low=0.0, high=1e9, sigma=1.0)\n    return m\n"))
    with pytest.warns(FloatResolutionWarning, match=r"state 'pos': carried as 1e\+09, float spacing 64"):
        build_model(str(path), precision="float")
    with warnings.catch_warnings():
        warnings.simplefilter("error", FloatResolutionWarning)
        build_model(str(path))                                                      # double: silent
