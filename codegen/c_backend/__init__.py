"""The C backend: Bundle -> C99 translation units, header, Makefile (the flight bundle Python loads).

The bundle is one translation unit per CasADi function: ``<model>_k_<kernel>.c`` per kernel and
``<model>_fn_<name>.c`` per function the kernels call (f_d and its Jacobian, h, sigma-point
propagation, ...), each CasADi's code of that one function (every helper ``static``); plus
``<model>_api.c`` with the documented API below, ``<model>_hash.c`` (the content hash, alone
because every build changes it) and ``<model>.h``. A function is defined once and declared where
it is called (a filter step calls its predict and update units, both predicts call f_d's), so an
edit recompiles only the functions whose code changed (:func:`.units.function_units`) and the
units compile in parallel. Function units include nothing of ours (their text is all that
determines their object); their entry points are ``SYMKF_INTERNAL`` (hidden: ``nm -D lib<model>.so`` lists
only the header's API, and a build with ``ekf_lockstep``/``ukf_lockstep`` also the host library's
``_run_lockstep`` loops of :mod:`.lockstep`, which the bundle's Makefile compiles to nothing). For each kernel (:mod:`.api`):

- ``int <model>_<kernel>(inputs..., outputs...)``: the public function. Scalar inputs (t, dt,
  kappa, a one-component mask) are passed by value, arrays as ``const casadi_real name[size]``,
  zero-size arguments are left out. Work space is on the stack (sizes fixed at generation);
  results go to stack temporaries and are copied to the outputs only on success, so outputs may
  alias inputs (in-place x, P) and are untouched on failure; returns 0 or a SYMKF_ERR_* code.
  SYMKF_GATED (an update refused by its chi-square gate) is not a failure: the outputs are
  written (x, P as before the update) and the code returned.
- ``int <model>_<kernel>_v(casadi_real *const *args)``: the binding entry for foreign-function
  interfaces (the Python runtime): every input and output of the manifest, in its order, as one
  pointer array (scalars and zero-size arguments included, as pointers).
- ``int <model>_<kernel>_run(n_steps, ...)`` for filter-step kernels: the whole time loop in C.

No heap, no mutable globals, every function re-entrant. Math functions are called through
``SYMKF_<NAME>`` macros that name the double or the float function explicitly (``-DSYMKF_FLOAT``
selects float; no <tgmath.h>). The header's stack figures are filled in after compiling, from
the compiler's own call graphs of the units (``-fcallgraph-info=su``: each function's frame plus
its worst call path across the units).

One job per module: :mod:`.names` (file and function names, the rule that keeps them apart, the
generated-file notice), :mod:`.casadi_text` (passes over CasADi's C), :mod:`.api`, :mod:`.header`,
:mod:`.units`, :mod:`.makefile` (flags and Makefile), :mod:`.stack` (stack figures) and
:mod:`.template_util`, which reads the static C and Make text in ``templates/``.
"""
