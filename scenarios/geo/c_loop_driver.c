#include <stdio.h>
#include "geo_satellite.h"
/* Instruction counts of the Koreasat-3 CD-EKF (symkf bench geo --instructions), run under callgrind.
   stdin: x0[17] P0[289] Q[289] R[16] n, then n lines: dt u[4] z[4] (gyro outputs, every step).
   argv[1]: steps; argv[2]: part: predict (one geo_satellite_cd_ekf_predict per step), run (the
   forward geo_satellite_cd_ekf_step_gyro_run over the steps) or backward (that run, then the
   smoother's backward pass geo_satellite_cd_ekf_smooth_run over it). stdout: the first error code. */
#define NX 17
#define MAX_STEPS 1200
static int rd(double *v, int n) { int i; for (i = 0; i < n; ++i) if (scanf("%lf", &v[i]) != 1) return 0; return 1; }
static double T[MAX_STEPS], DT[MAX_STEPS], U[4 * MAX_STEPS], Z[4 * MAX_STEPS], M[4 * MAX_STEPS];
static double XH[NX * MAX_STEPS], PH[NX * NX * MAX_STEPS], XS[NX * MAX_STEPS], PS[NX * NX * MAX_STEPS];
static int SH[MAX_STEPS], SS[MAX_STEPS];
static double x0[NX], P0[NX * NX], Q[NX * NX], R[16], x[NX], P[NX * NX];
static const double gate[4] = {0, 0, 0, 0};
int main(int argc, char **argv) {
  int n, k, i, steps, code = 0;
  char part = argc > 2 ? argv[2][0] : 'r';
  if (argc < 2 || sscanf(argv[1], "%d", &steps) != 1 || !rd(x0, NX) || !rd(P0, NX * NX) || !rd(Q, NX * NX) ||
      !rd(R, 16) || scanf("%d", &n) != 1 || n > MAX_STEPS || steps > n) return 2;
  for (k = 0; k < n; ++k) {
    if (!rd(&DT[k], 1) || !rd(&U[4 * k], 4) || !rd(&Z[4 * k], 4)) return 2;
    T[k] = k ? T[k - 1] + DT[k - 1] : 0.0;
    for (i = 0; i < 4; ++i) M[4 * k + i] = 1.0;
  }
  if (part == 'p') {
    for (i = 0; i < NX; ++i) x[i] = x0[i];
    for (i = 0; i < NX * NX; ++i) P[i] = P0[i];
    for (k = 0; k < steps && !code; ++k) code = geo_satellite_cd_ekf_predict(T[k], DT[k], x, P, &U[4 * k], Q, x, P);
  } else {
    code = geo_satellite_cd_ekf_step_gyro_run(steps, T, DT, x0, P0, U, Q, Z, M, R, gate, XH, PH, SH);
    if (part == 'b' && !code) code = geo_satellite_cd_ekf_smooth_run(steps, T, DT, XH, PH, U, Q, SH, XS, PS, SS);
  }
  printf("%d\n", code);
  return 0;
}
