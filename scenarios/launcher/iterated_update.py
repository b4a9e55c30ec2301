"""The iterated EKF update (codegen/families/iterated.py) on the launcher's large-error cases.

    python -m symkf.scenarios.launcher.iterated_update [--runs 100] [--iterations 1 3 5] [--json FILE]

For each iteration count, the campaign (preset ``correct``, seed 2005, the draws of ``symkf
compare launcher``) at 20 and 10 Hz, large initial error (eq 10), through the EKF built with
``ekf_iterations`` = that count (1: the plain EKF): whole-flight RMS of r and V (eq 11) and the
fraction of time steps whose average NEES is inside its 95 % chi-square band (whole flight and
outside the event windows), from :func:`symkf.scenarios.launcher.campaign.consistency`.
"""
from __future__ import annotations

import argparse
import json

from symkf.scenarios.launcher import campaign as C


def table(runs: int, counts=(1, 3), seed: int = 2005, rates=(20, 10)) -> dict:
    """{count: {"<rate>Hz": {r_rms_m, V_rms_m_s, mean_nees, inside_band, inside_band_quiet, failed_steps}}}."""
    out = {}
    for count in counts:
        build = {} if count == 1 else {"ekf_iterations": count}
        results = C.Campaign(runs, seed, rates=rates, build=build).run()
        for result in results:
            if result.case.initial_error != "large":
                continue
            whole = result.whole_flight("ekf")
            nees = C.consistency(result, "ekf")
            per_run = result.per_run("ekf")
            out.setdefault(count, {})[f"{result.case.rate_hz}Hz"] = {
                "r_rms_m": float(whole[3]), "V_rms_m_s": float(whole[0]), "mean_nees": nees["mean_nees"],
                "inside_band": nees["fraction_inside_band"],
                "inside_band_quiet": nees["fraction_inside_band_outside_event_windows"],
                "failed_steps": int(per_run[:, C.PER_RUN_COLUMNS.index("failed_steps")].sum()),
                "diverged_runs": int(per_run[:, C.PER_RUN_COLUMNS.index("diverged")].sum()), "runs": runs}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--iterations", type=int, nargs="+", default=[1, 3])
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    result = table(args.runs, tuple(args.iterations))
    print(f"{'iterations':>10s} {'case':>6s} {'r RMS (m)':>10s} {'V RMS (m/s)':>11s} {'mean NEES':>9s} "
          f"{'in band':>8s} {'in band (quiet)':>15s} {'failed':>6s} {'diverged':>8s}")
    for count, rows in result.items():
        for case, row in rows.items():
            print(f"{count:10d} {case:>6s} {row['r_rms_m']:10.3f} {row['V_rms_m_s']:11.4f} {row['mean_nees']:9.2f} "
                  f"{row['inside_band']:8.2f} {row['inside_band_quiet']:15.2f} {row['failed_steps']:6d} "
                  f"{row['diverged_runs']:8d}")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(result, handle, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
