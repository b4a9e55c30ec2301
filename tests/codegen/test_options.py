"""The typed codegen options: every option declared once with its type, default and meaning;
``CodegenConfig.with_overrides`` refuses unknown names and values of the wrong type."""
import pytest

from symkf.codegen.spec import CodegenConfig, ConfigError, codegen_options


def test_every_option_is_listed_with_type_default_meaning_and_reader():
    listed = {o.name: o for o in codegen_options()}
    for name in ("rk4_substeps", "optimization", "precision", "scaling", "split_events", "ekf_integrator",
                 "ukf_substeps", "manifold_chart", "manifold_run_variants", "unit_optimization"):
        assert name in listed
    assert (listed["ekf_substeps"].type, listed["ekf_substeps"].default) == (int, 1)
    assert listed["manifold_chart"].default == "rotation_vector" and listed["manifold_chart"].meaning
    assert {"family 'mekf'", "family 'mukf'", "family 'sukf'", "family 'aukf'"} <= set(listed["manifold_side"].readers)


def test_with_overrides_checks_names_and_types_and_keeps_the_extra_tuple():
    config = CodegenConfig().with_overrides(manifold_side="left", ekf_substeps=2, split_events=False)
    assert config.extra == (("ekf_substeps", 2), ("manifold_side", "left"), ("split_events", False))
    assert config.get("manifold_side") == "left" and config.get("manifold_chart", "default") == "default"
    with pytest.raises(ConfigError, match=r"unknown codegen option\(s\) \['manifold_sides'\]; known: .*manifold_side"):
        CodegenConfig().with_overrides(manifold_sides="left")
    for bad in ({"ekf_substeps": 2.0}, {"ekf_substeps": True}, {"split_events": 1}, {"manifold_side": 1}):
        with pytest.raises(ConfigError, match="expected a value of type"):
            CodegenConfig().with_overrides(**bad)
