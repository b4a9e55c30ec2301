#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "marg_mekf.h"
/* driver PART N < samples.bin: N samples of the BROAD trial through one part of the MEKF's API */
enum { HEAD = 7 + 36 + 36 + 49 + 7, ROW = 22 };
int main(int argc, char **argv) {
  double head[HEAD], *rows, x[7], P[36], y[7], S[49], *xh, *Ph;
  int n, k, code = 0, *status;
  if (argc != 3 || fread(head, sizeof(double), HEAD, stdin) != HEAD) return 2;
  n = atoi(argv[2]);
  rows = malloc(sizeof(double) * ROW * (size_t) n);
  if (!rows || fread(rows, sizeof(double), ROW * (size_t) n, stdin) != ROW * (size_t) n) return 3;
  memcpy(x, head, sizeof x); memcpy(P, head + 7, sizeof P);
  if (!strcmp(argv[1], "run")) {
    double *t = malloc(8 * (size_t) n), *dt = malloc(8 * (size_t) n), *u = malloc(24 * (size_t) n),
           *q = malloc(24 * (size_t) n), *z = malloc(56 * (size_t) n), *mask = malloc(56 * (size_t) n);
    xh = malloc(56 * (size_t) n); Ph = malloc(288 * (size_t) n); status = malloc(sizeof(int) * (size_t) n);
    for (k = 0; k < n; ++k) {
      const double *r = rows + ROW * k;
      t[k] = r[0]; dt[k] = r[1]; memcpy(u + 3 * k, r + 2, 24); memcpy(q + 3 * k, r + 5, 24);
      memcpy(z + 7 * k, r + 8, 56); memcpy(mask + 7 * k, r + 15, 56);
    }
    code = marg_mekf_mekf_run_marg_run(n, t, dt, x, P, u, head + 43, q, z, mask, head + 79, head + 128, xh, Ph, status);
  } else {
    for (k = 0; k < n && (code == 0 || code == SYMKF_GATED); ++k) {
      const double *r = rows + ROW * k;
      if (!strcmp(argv[1], "predict"))
        code = marg_mekf_mekf_predict(r[0], r[1], x, P, r + 2, head + 43, x, P);
      else if (!strcmp(argv[1], "update"))
        code = marg_mekf_mekf_update_marg(r[0], x, P, r + 2, r + 5, r + 8, r + 15, head + 79, head + 128, x, P, y, S);
      else
        code = marg_mekf_mekf_step_marg(r[0], r[1], x, P, r + 2, head + 43, r + 5, r + 8, r + 15, head + 79,
                                       head + 128, x, P, y, S);
    }
  }
  printf("%d\n", code);
  return 0;
}
