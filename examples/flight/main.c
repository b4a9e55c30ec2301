/* Flight-software example: the launcher EKF over a recorded radar pass, with only the generated
 * bundle (build/launcher/: launcher.h, launcher_*.c), a C99 compiler and libm.
 *
 *   python -m symkf.scenarios.launcher.record --out radar.txt     (or any record in that format)
 *   make && ./flight radar.txt > estimates.txt
 *
 * The record holds the initial estimate x0, P0, the tuning Q, R and one line per radar sample:
 * t dt q[NQ] z[NZ] mask[NZ]. Each sample is one call of the generated step function, as a flight
 * loop would make it: predict from t to t + dt, then update with z taken at t + dt (t is the time
 * of the previous estimate, not the measurement time; see launcher.h). x and P are updated in
 * place; on a refused step (non-zero code) they are untouched and the loop goes on.
 * Output: one line per sample: k, the step's code, then x after it (17 significant digits).
 *
 * Build with -DSYMKF_TRAP_FPE (glibc) to run with floating-point traps enabled: any division by
 * zero, invalid operation or overflow in the generated code then stops the program (SIGFPE). */
#ifdef SYMKF_TRAP_FPE
#define _GNU_SOURCE
#include <fenv.h>
#endif
#include <stdio.h>
#include <string.h>
#include "launcher.h"

/* The radar measurement this example filters (the campaign's WGS-84 stations). */
#define NX LAUNCHER_NX
#define NZ LAUNCHER_NZ_RADAR_WGS84
#define NQ LAUNCHER_NQ_RADAR_WGS84
#define STEP launcher_ekf_step_radar_wgs84

static int read_numbers(FILE *in, casadi_real *values, int count) {
  int i;
  double value;
  for (i = 0; i < count; ++i) {
    if (fscanf(in, "%lf", &value) != 1) return 0;
    values[i] = (casadi_real) value;
  }
  return 1;
}

int main(int argc, char **argv) {
  static const casadi_real p[LAUNCHER_NP] = LAUNCHER_P_DEFAULT;    /* guidance parameters, header defaults */
  static const casadi_real gate[NZ] = {0};                         /* no chi-square gate */
  casadi_real x[NX], P[NX * NX], Q[NX * NX], R[NZ * NZ];
  casadi_real step[2 + NQ + 2 * NZ], y[NZ], S[NZ * NZ];
  char format[64], model[64], measurement[64];
  int n, nx, nz, nq, k, i, code, refused = 0;
  FILE *in;
  if (argc != 2 || (in = fopen(argv[1], "r")) == NULL) {
    fprintf(stderr, "usage: %s RECORD (written by python -m symkf.scenarios.launcher.record)\n", argv[0]);
    return 2;
  }
#ifdef SYMKF_TRAP_FPE
  feenableexcept(FE_DIVBYZERO | FE_INVALID | FE_OVERFLOW);
#endif
  if (fscanf(in, "%63s %63s %63s", format, model, measurement) != 3 || strcmp(format, "symkf-radar-record-1") != 0
      || strcmp(measurement, "radar_wgs84") != 0 || fscanf(in, "%d %d %d %d", &n, &nx, &nz, &nq) != 4
      || nx != NX || nz != NZ || nq != NQ) {
    fprintf(stderr, "%s: not a launcher radar_wgs84 record with %d states, %d components, %d station parameters\n",
            argv[1], NX, NZ, NQ);
    return 2;
  }
  if (!read_numbers(in, x, NX) || !read_numbers(in, P, NX * NX) || !read_numbers(in, Q, NX * NX)
      || !read_numbers(in, R, NZ * NZ)) {
    fprintf(stderr, "%s: truncated header\n", argv[1]);
    return 2;
  }
  for (k = 0; k < n; ++k) {
    const casadi_real *q = step + 2, *z = step + 2 + NQ, *mask = step + 2 + NQ + NZ;
    if (!read_numbers(in, step, 2 + NQ + 2 * NZ)) {
      fprintf(stderr, "%s: truncated at sample %d\n", argv[1], k);
      return 2;
    }
    code = STEP(step[0], step[1], x, P, p, Q, q, z, mask, R, gate, x, P, y, S);
    refused += code != SYMKF_OK && code != SYMKF_GATED;
    printf("%d %d", k, code);
    for (i = 0; i < NX; ++i) printf(" %.17g", (double) x[i]);
    printf("\n");
  }
  fclose(in);
  fprintf(stderr, "%d samples, %d refused steps; final r = %.3f m, V = %.3f m/s\n", n, refused,
          (double) x[LAUNCHER_X_R], (double) x[LAUNCHER_X_V]);
  return 0;
}
