"""The lockstep units of a bundle: one C unit per fused step and per smoother backward step
(c_backend/lockstep.py, c_backend/smooth_lockstep.py), each compiled only with SYMKF_LANES."""
from __future__ import annotations

from ..spec import STATUS_GATED, STATUS_OK
from .lockstep import LockstepSpec, lockstep_file, lockstep_function
from .smooth_lockstep import smooth_lockstep_function
from .vector_c import PRELUDE, VECTOR_MATH_DECLARATIONS, WIDTH


def lockstep_units(model: str, specs: list[LockstepSpec], notice: str) -> dict[str, str]:
    """One unit per fused step (they compile in parallel): its loop and its ``_lockstep_available``,
    compiled only with SYMKF_LANES."""
    return {lockstep_file(model, spec.kernel.name): lockstep_unit(model, spec, notice) for spec in specs}


def lockstep_unit(model: str, spec: LockstepSpec, notice: str) -> str:
    name = f"{model}_{spec.kernel.name}"
    loop = smooth_lockstep_function(model, spec) if spec.kernel.backward else lockstep_function(model, spec)
    return "\n".join([
        f"/* {notice}", f" * {spec.kernel.name}: Monte Carlo runs stepped in lockstep, 4 per AVX2 vector, for the host",
        " * library only (codegen/c_backend/lockstep.py): compiled to nothing without SYMKF_LANES (the flight",
        " * bundle's Makefile). */",
        "#include <math.h>", "#include <string.h>", "",
        f"typedef int {name}_lockstep_unit;       /* (a unit is never empty: ISO C) */", "",
        "#if defined(SYMKF_LANES) && defined(__GNUC__) && defined(__x86_64__)",
        PRELUDE,
        *([VECTOR_MATH_DECLARATIONS] if spec.vector_math else []),
        "typedef double casadi_real;          /* (the API's scalar type: lockstep is double only) */",
        f"#define SYMKF_LOCKSTEP_OK {STATUS_OK}",
        f"#define SYMKF_LOCKSTEP_GATED {STATUS_GATED}",
        "static int symkf_lockstep_finite_value(double v) { unsigned long long b; memcpy(&b, &v, 8); "
        "return (b & 0x7ff0000000000000ULL) != 0x7ff0000000000000ULL; }",
        "static int symkf_lockstep_finite(const double *v, int n) { int i, ok = 1; "
        "for (i = 0; i < n; ++i) ok &= symkf_lockstep_finite_value(v[i]); return ok; }",
        "/* a lane is worth the vector step if its inputs are finite and no branch condition is set in it */",
        "__attribute__((target(\"avx2\"))) static int lanes_wanted(symkf_v4 flag, const int *ok) { int l, any = 0; "
        f"for (l = 0; l < {WIDTH}; ++l) any |= ok[l] && flag[l] == 0.; return any; }}", "",
        loop,
        f"int {name}_lockstep_available(void) {{ return __builtin_cpu_supports(\"avx2\") ? 1 : 0; }}",
        "#endif", ""])
