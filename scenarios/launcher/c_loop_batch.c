#include <string.h>
#include "launcher.h"
/* Steps k0 .. k0 + count - 1 of the record (n rows: T, Z[3], QS[2]), step k with row j = 1 + k % (n - 1),
   from x, P (restarting from x0, P0 at j = 1): launcher_<filter>_step_radar, mask all ones, no gate,
   as the Python paths call it. Returns the OR of the status codes. */
int c_loop_batch(int ukf, int k0, int count, int n, const double *T, const double *Z, const double *QS,
                 const double *x0, const double *P0, double *x, double *P, const double *p, const double *Q,
                 const double *R, double kappa, double dt) {
  static const double mask[3] = {1, 1, 1}, gate[3] = {0, 0, 0};
  double y[3], S[9];
  int k, code = 0;
  for (k = k0; k < k0 + count; ++k) {
    int j = 1 + k % (n - 1);
    if (j == 1) { memcpy(x, x0, 6 * sizeof *x); memcpy(P, P0, 36 * sizeof *P); }
    code |= ukf ? launcher_ukf_step_radar(T[j - 1], dt, x, P, p, Q, &QS[2 * j], &Z[3 * j], mask, R, gate, kappa, x, P, y, S)
                : launcher_ekf_step_radar(T[j - 1], dt, x, P, p, Q, &QS[2 * j], &Z[3 * j], mask, R, gate, x, P, y, S);
  }
  return code;
}
