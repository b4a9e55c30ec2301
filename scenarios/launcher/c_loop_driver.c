#include <stdio.h>
#include <string.h>
#include <time.h>
#include "launcher.h"
/* stdin: x0[6] P0[36] Q[36] R[9] kappa p[6] n_base, n_base lines t z[3] q[2].
   argv[1]: ekf|ukf, argv[2]: steps, argv[3] (optional) part: step (default), predict, update, run, backward,
   lockstep (launcher_<filter>_step_radar_run_lockstep over LANES runs of the record, each its copy, after the run),
   smooth-lockstep (that, then launcher_<filter>_smooth_run_lockstep over the LANES runs).
   step/predict/update: one call of launcher_<filter>_<part>[_radar] per step; run: one call of
   launcher_<filter>_step_radar_run over all the steps; backward: that run, then the smoother's
   backward pass launcher_<filter>_smooth_run over it. The record restarts from x0, P0 at its end.
   stdout: wall µs per step (median over batches of 100 steps), the failure code, this thread's CPU µs
   per step (median over the batches). */
static double clock_s(clockid_t id) { struct timespec ts; clock_gettime(id, &ts); return ts.tv_sec + 1e-9 * ts.tv_nsec; }
static double now(void) { return clock_s(CLOCK_MONOTONIC); }
static double cpu_now(void) { return clock_s(CLOCK_THREAD_CPUTIME_ID); }
static void sort(double *v, int n) { int i; for (i = 1; i < n; ++i) { double a = v[i]; int m = i - 1; while (m >= 0 && v[m] > a) { v[m + 1] = v[m]; --m; } v[m + 1] = a; } }
static int rd(double *v, int n) { int i; for (i = 0; i < n; ++i) if (scanf("%lf", &v[i]) != 1) return 0; return 1; }
static double T[20000], Z[60000], QS[40000];
static double RT[20000], RDT[20000], RZ[60000], RQ[40000], RM[60000], XH[120000], PH[720000];
static int SH[20000], SS[20000];
static double XS[120000], PS[720000];
static double x0[6], P0[36], x[6], P[36], Q[36], R[9], kappa, p[6], y[3], S[9], mask[3] = {1, 1, 1}, gate[3] = {0, 0, 0};
static int call(int ukf, char part, int j, double dt) {
  const double *q = &QS[2 * j], *z = &Z[3 * j];
  if (part == 'p') return ukf ? launcher_ukf_predict(T[j - 1], dt, x, P, p, Q, kappa, x, P)
                              : launcher_ekf_predict(T[j - 1], dt, x, P, p, Q, x, P);
  if (part == 'u') return ukf ? launcher_ukf_update_radar(T[j], x, P, p, q, z, mask, R, gate, kappa, x, P, y, S)
                              : launcher_ekf_update_radar(T[j], x, P, p, q, z, mask, R, gate, x, P, y, S);
  return ukf ? launcher_ukf_step_radar(T[j - 1], dt, x, P, p, Q, q, z, mask, R, gate, kappa, x, P, y, S)
             : launcher_ekf_step_radar(T[j - 1], dt, x, P, p, Q, q, z, mask, R, gate, x, P, y, S);
}
static int run(int ukf, int n, int steps) {
  int k, i;
  if (steps > n - 1 || steps > 20000) return -1;
  for (k = 0; k < steps; ++k) {
    RT[k] = T[k]; RDT[k] = T[k + 1] - T[k];
    for (i = 0; i < 3; ++i) { RZ[3 * k + i] = Z[3 * (k + 1) + i]; RM[3 * k + i] = 1; }
    for (i = 0; i < 2; ++i) RQ[2 * k + i] = QS[2 * (k + 1) + i];
  }
  return ukf ? launcher_ukf_step_radar_run(steps, RT, RDT, x0, P0, p, Q, RQ, RZ, RM, R, gate, kappa, XH, PH, SH)
             : launcher_ekf_step_radar_run(steps, RT, RDT, x0, P0, p, Q, RQ, RZ, RM, R, gate, XH, PH, SH);
}
#ifdef SYMKF_LOCKSTEP        /* linked against a library built with ekf_lockstep */
#define LANES 4
#define LOCKSTEP_STEPS 2000
/* the host library's lockstep loop (not in the bundle's header: codegen/c_backend/lockstep.py) */
int launcher_ekf_step_radar_run_lockstep(int n_runs, int n_steps, const double *t, const double *dt, const double *x0,
    const double *P0, const double *u, const double *p, const double *Q, const double *q, const double *z,
    const double *mask, const double *R, const double *gate, double *x_hist, double *P_hist, double *y_hist,
    double *S_hist, int *status_hist);
int launcher_ukf_step_radar_run_lockstep(int n_runs, int n_steps, const double *t, const double *dt, const double *x0,
    const double *P0, const double *u, const double *p, const double *Q, const double *q, const double *z,
    const double *mask, const double *R, const double *gate, const double *kappa, double *x_hist, double *P_hist,
    double *y_hist, double *S_hist, int *status_hist);
int launcher_ekf_smooth_run_lockstep(int n_runs, int n_steps, const double *t, const double *dt,
    const double *x_hist, const double *P_hist, const double *u, const double *p, const double *Q,
    const int *status_hist, double *xs_hist, double *Ps_hist, int *smooth_status);
int launcher_ukf_smooth_run_lockstep(int n_runs, int n_steps, const double *t, const double *dt,
    const double *x_hist, const double *P_hist, const double *u, const double *p, const double *Q,
    const double *kappa, const int *status_hist, double *xs_hist, double *Ps_hist, int *smooth_status);
static double LXS[LANES * LOCKSTEP_STEPS * 6], LPS[LANES * LOCKSTEP_STEPS * 36];
static int LSS[LANES * LOCKSTEP_STEPS];
static double LZ[LANES * LOCKSTEP_STEPS * 3], LM[LANES * LOCKSTEP_STEPS * 3], LX[LANES * LOCKSTEP_STEPS * 6];
static double LP[LANES * LOCKSTEP_STEPS * 36], LY[LANES * LOCKSTEP_STEPS * 3], LS[LANES * LOCKSTEP_STEPS * 9];
static int LST[LANES * LOCKSTEP_STEPS];
static int lockstep(int ukf, int n, int steps) {
  int r, i, code;
  if (steps > LOCKSTEP_STEPS) return -1;
  code = run(ukf, n, steps);               /* fills the record (and runs it once: the same for every count) */
  for (r = 0; r < LANES; ++r)
    for (i = 0; i < 3 * steps; ++i) { LZ[r * 3 * steps + i] = RZ[i]; LM[r * 3 * steps + i] = 1; }
  if (ukf) return code | launcher_ukf_step_radar_run_lockstep(LANES, steps, RT, RDT, x0, P0, 0, p, Q, RQ, LZ, LM, R,
                                                              gate, &kappa, LX, LP, LY, LS, LST);
  return code | launcher_ekf_step_radar_run_lockstep(LANES, steps, RT, RDT, x0, P0, 0, p, Q, RQ, LZ, LM, R, gate,
                                                     LX, LP, LY, LS, LST);
}
static int smooth_lockstep(int ukf, int n, int steps) {
  int code = lockstep(ukf, n, steps);
  if (code) return code;
  return ukf ? launcher_ukf_smooth_run_lockstep(LANES, steps, RT, RDT, LX, LP, 0, p, Q, &kappa, LST, LXS, LPS, LSS)
             : launcher_ekf_smooth_run_lockstep(LANES, steps, RT, RDT, LX, LP, 0, p, Q, LST, LXS, LPS, LSS);
}
#else
static int lockstep(int ukf, int n, int steps) { (void)ukf; (void)n; (void)steps; return -1; }
static int smooth_lockstep(int ukf, int n, int steps) { (void)ukf; (void)n; (void)steps; return -1; }
#endif
static int backward(int ukf, int steps) {
  return ukf ? launcher_ukf_smooth_run(steps, RT, RDT, XH, PH, p, Q, kappa, SH, XS, PS, SS)
             : launcher_ekf_smooth_run(steps, RT, RDT, XH, PH, p, Q, SH, XS, PS, SS);
}
int main(int argc, char **argv) {
  double dt = 0.05, batches[1000], cpu_batches[1000], start, cpu_start;
  int n, i, k, b, nb, steps, ukf, code = 0;
  char part = argc > 3 ? (strcmp(argv[3], "smooth-lockstep") ? argv[3][0] : 'm') : 's';
  if (argc < 3 || !rd(x0, 6) || !rd(P0, 36) || !rd(Q, 36) || !rd(R, 9) || !rd(&kappa, 1) || !rd(p, 6)) return 2;
  ukf = argv[1][0] == 'u';
  if (sscanf(argv[2], "%d", &steps) != 1 || scanf("%d", &n) != 1 || n > 20000) return 2;
  for (i = 0; i < n; ++i) if (!rd(&T[i], 1) || !rd(&Z[3 * i], 3) || !rd(&QS[2 * i], 2)) return 2;
  if (part == 'r' || part == 'b' || part == 'l' || part == 'm') {
    start = now(), cpu_start = cpu_now();
    code = part == 'l' ? lockstep(ukf, n, steps) : part == 'm' ? smooth_lockstep(ukf, n, steps) : run(ukf, n, steps);
    if (part == 'b' && code == 0) code = backward(ukf, steps);
    printf("%.6f %d %.6f\n", 1e6 * (now() - start) / steps, code, 1e6 * (cpu_now() - cpu_start) / steps);
    return 0;
  }
  memcpy(x, x0, sizeof x); memcpy(P, P0, sizeof P);
  nb = steps / 100 > 1000 ? 1000 : steps / 100;
  for (b = 0, k = 0; b < nb; ++b) {
    start = now(), cpu_start = cpu_now();
    for (i = 0; i < 100; ++i, ++k) {
      int j = 1 + k % (n - 1);
      if (j == 1) { memcpy(x, x0, sizeof x); memcpy(P, P0, sizeof P); }
      code |= call(ukf, part, j, dt);
    }
    batches[b] = (now() - start) / 100;
    cpu_batches[b] = (cpu_now() - cpu_start) / 100;
  }
  sort(batches, nb);
  sort(cpu_batches, nb);
  printf("%.6f %d %.6f\n", 1e6 * batches[nb / 2], code, 1e6 * cpu_batches[nb / 2]);
  return 0;
}
