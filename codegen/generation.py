"""Model -> kernels (CasADi Functions) -> the C units, header, Makefile and manifest of a bundle.

A build folder holds the C units (``<name>_api.c``, ``<name>_hash.c``, one ``<name>_k_<kernel>.c``
per kernel and one ``<name>_fn_<function>.c`` per function the kernels call), ``<name>.h``,
``Makefile`` and ``manifest.json``; :func:`write_bundle` writes them, the compiler
(:mod:`symkf.codegen.compilation`) adds the library.
"""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import casadi as ca

from symkf.models import Model, get_model
from symkf.models.checks import check_parameters_used
from . import families  # noqa: F401  (families register themselves on import)
from .c_backend import header as c_header, lanes as c_lanes, lockstep as c_lockstep, makefile as c_makefile, units as c_units
from .c_backend.names import check_c_names
from .compilation import UnitCompiler, compile_flags, compiler_identity, unit_optimization
from .errors import BuildError
from .hashing import symkf_version
from .families.framework import FAMILIES, LONG_COMPILE, check_quaternions, model_kernels
from .model_functions import ModelFunctions, Symbols
from .scaling import model_for
from .spec import Bundle, CodegenConfig

#: Filter families that see the parameters only through the model's equations: for a model with
#: only these, a parameter no equation uses is an authoring mistake (the MARG filter's gain is a
#: parameter of the filter).
EQUATION_ONLY_FAMILIES = frozenset({"ekf", "ukf", "cd_ekf"})


def default_config(model: Model) -> CodegenConfig:
    """The model's own codegen defaults (``Model.codegen_defaults``), no overrides."""
    return CodegenConfig().with_overrides(**model.codegen_defaults)


def make_config(model, **overrides) -> CodegenConfig:
    """The model's codegen defaults (``Model.codegen_defaults``) with overrides applied."""
    return config_for(get_model(model), **overrides)


def config_for(model: Model, **overrides) -> CodegenConfig:
    """:func:`make_config` of a Model :func:`~symkf.models.get_model` returned (not validated again)."""
    return CodegenConfig().with_overrides(**{**model.codegen_defaults, **overrides})


def generate(model, config: CodegenConfig | None = None) -> Bundle:
    """Model -> kernels (CasADi Functions) for every filter family the model asks for."""
    model = get_model(model)
    return generate_validated(model, config or default_config(model))


def check_families(model: Model) -> None:
    """Every family the model asks for exists, and none would treat a quaternion state as a
    vector unless the model says so (:func:`~symkf.codegen.families.framework.check_quaternions`)."""
    for family in model.filters:
        if family not in FAMILIES:
            raise BuildError(f"model '{model.name}' asks for filter family '{family}'; known: {sorted(FAMILIES)}")
    try:
        check_quaternions(model)
    except ValueError as exc:
        raise BuildError(str(exc)) from None


def generate_validated(model: Model, config: CodegenConfig, on_part=None) -> Bundle:
    """:func:`generate` of a Model :func:`~symkf.models.get_model` returned (not validated again:
    the build and the runtime's VM backend have it). The kernels are made
    in parts: the model's own (f, f_d, F, h, H), then each filter family's, in the model's order.
    ``on_part(index, part)``, if given, receives each part's bundle as soon as it is made (a build
    starts compiling its units while the next part is generated); the families with the longest
    compile (:data:`~symkf.codegen.families.framework.LONG_COMPILE`) are made first."""
    if set(model.filters) <= EQUATION_ONLY_FAMILIES:
        check_parameters_used(model)
    model = model_for(model, config)
    check_families(model)
    symbols, functions = Symbols(model), ModelFunctions(model, config)
    own = model_kernels(model, symbols, functions)
    if on_part is not None:
        on_part(0, Bundle(model.name, list(own), config, model.describe()))
    made, lanes, lockstep = {}, (), ()
    for family in sorted(model.filters, key=lambda name: name not in LONG_COMPILE):    # stable: else the model's order
        made[family] = FAMILIES[family](model, symbols, functions)
        if family == "ukf":                 # its sigma points in SIMD lanes (host library only)
            lanes = c_lanes.specs_of(functions, config)
        if family in ("ekf", "ukf") and c_lockstep.enabled(config, family):    # runs in lockstep (host library only)
            lockstep += c_lockstep.specs_of(made[family].kernels, made[family].filters, functions.for_filter(family),
                                            c_lockstep.uses_vector_math(config, family))
        if on_part is not None:
            on_part(1 + model.filters.index(family), Bundle(model.name, list(made[family].kernels), config,
                                                             model.describe(), lanes=lanes))
    kernels = own + [k for family in model.filters for k in made[family].kernels]
    filters = [f for family in model.filters for f in made[family].filters]
    check_c_names(model.name, kernels, model.measurements)
    parts = (len(own),) + tuple(len(made[family].kernels) for family in model.filters)
    return Bundle(model.name, kernels, config, model.describe(), filters, parts, lanes, lockstep)


def write_bundle(bundle: Bundle, directory: Path, key: str, generated: str, cc: str,
                 units: UnitCompiler | None = None, per_part: list[dict[str, str]] | None = None) -> None:
    """Write the translation units (through ``units``, which starts compiling them), the header,
    the Makefile and a provisional manifest.json (no library yet; ``sources`` lists the units,
    the API unit first). ``per_part``: the units of each part of the bundle, if already made."""
    name = bundle.model_name
    sources = c_units.units(bundle, key, per_part)
    if units is not None:
        units.add(sources)
    else:
        for file, text in sources.items():
            (directory / file).write_text(text)
    (directory / f"{name}.h").write_text(c_header.header(bundle, key, cc, " ".join(compile_flags(bundle.config))))
    own = {file: flags for file in sources if (flags := unit_optimization(bundle.config, file)) != bundle.config.optimization}
    (directory / "Makefile").write_text(c_makefile.makefile(name, bundle.config.optimization, list(sources), own,
                                                                    bundle.description.get("source", "")))
    manifest = {"model": name, "content_hash": key, "generated_hash": generated,
                "symkf_version": symkf_version(), "casadi_version": ca.__version__,
                "compiler": cc, "compiler_identity": compiler_identity(cc), "flags": c_makefile.STRICT_FLAGS,
                "optimization": bundle.config.optimization, "unit_optimization": own, "config": asdict(bundle.config),
                "description": bundle.description, "library": f"lib{name}.so", "sources": list(sources),
                "kernels": [k.as_dict() for k in bundle.kernels],
                "filters": [f.as_dict() for f in bundle.filters]}
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=1))
