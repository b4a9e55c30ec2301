"""How the C API passes a kernel's arguments (:func:`passing`, also the Python runtime's rule) and
the finiteness tests of its inputs: shared by the API unit's wrappers and loops (``api.py``) and
a smoother's backward loop (``smooth_loop.py``)."""
from __future__ import annotations

from ..spec import Arg, Kernel


def passing(arg: Arg, kernel: Kernel, run: bool = False) -> str:
    """How an input is passed in the public C signature: 'omit' (zero-size), 'value' (a scalar)
    or 'pointer'. In a ``_run`` loop, carried and per-step inputs are always pointers (arrays of
    initial values or of n_steps blocks)."""
    if arg.size == 0:
        return "omit"
    if run and (arg.name in kernel.carried or arg.name in kernel.per_step):
        return "pointer"
    return "value" if arg.size == 1 else "pointer"


def sanitised_z(kernel: Kernel) -> bool:
    """True if the kernel has a measurement z with one mask entry per component."""
    sizes = {a.name: a.size for a in kernel.inputs}
    return sizes.get("z", 0) > 0 and sizes.get("mask") == sizes["z"]


def finite_terms(kernel: Kernel, names, where) -> list[str]:
    """``symkf_finite(...)`` of the named inputs (a sanitised z excluded: it is tested after masking);
    ``where(a)`` is the C expression of input ``a``'s first element's address."""
    return [f"symkf_finite({where(a)}, {a.size})" for a in kernel.inputs
            if a.name in names and passing(a, kernel) != "omit" and not (a.name == "z" and sanitised_z(kernel))]


def diagnosed(kernel: Kernel) -> list[Arg]:
    """The outputs of a run kernel besides its carried state (a step's y and S): a ``_run_diag``
    loop writes them per step into histories."""
    return [a for a in kernel.outputs[:-1] if a.name not in kernel.carried and a.size] if kernel.runnable else []
