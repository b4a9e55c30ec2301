 *
 * CONVENTIONS
 * - Matrices are dense and column-major; array sizes are in the prototypes.
 * - Scalars (t, dt, kappa, one-component values) are passed by value; arguments whose size is zero
 *   for this model are left out of the signatures (they stay, as pointers, in the _v binding entries).
 * - Outputs (name_out) may be the same arrays as the inputs (in-place x and P); on a non-zero
 *   return no output has been written.
 * - No heap, no global or static mutable data: every function is re-entrant. Each function's
 *   stack use is given by <NAME>_STACK_BYTES: the compiler's figure ({compiler}, flags
 *   {flags}, gcc -fcallgraph-info=su) for its own frame plus its deepest chain of calls into
 *   the bundle's units; calls into libm (sin, atan2, ...) are not included. -1 means not measured.
 * - Sources: {model}_api.c (these functions), {model}_hash.c, one {model}_k_<kernel>.c per kernel
 *   and one {model}_fn_<name>.c per function the kernels call (CasADi's code; entry points are
 *   SYMKF_INTERNAL, i.e. hidden). The Makefile builds them all.
 * - Only the functions declared here are exported (everything else is static or hidden).
 * - Single precision: compile every .c and your code with -DSYMKF_FLOAT (casadi_real becomes
 *   float and the float math functions sinf, sqrtf, ... are called explicitly). Link with -lm.
 *
 * TIME ARGUMENTS (each function's block below repeats the rule that applies to it)
 * - predict(t, dt): x and P are the estimate at t; the outputs are the estimate at t + dt.
 * - update(t):      t is the measurement time; x and P must already be the estimate at t.
 * - step(t, dt):    predict from t to t + dt, then update with z taken at t + dt. t is the time of
 *                   the previous estimate, NOT the measurement time.
 * - run:            step k covers [t[k], t[k] + dt[k]] with z[k] taken at t[k] + dt[k].
 * - f, h, jac_h(t): t is the instant at which x is given.
 */
