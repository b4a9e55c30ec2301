"""A thrust the model has wrong, filtered with and without estimating it (models/estimation.py).

    python -m symkf.scenarios.launcher.estimated_thrust [--runs 20] [--json FILE]

The truth flies with a stage-2 mass flow 5 % above the model's (``stage2_mass_flow``; stage-2
thrust = Isp g0 x mass flow, so 5 % more thrust and a 5 % faster mass depletion from ignition at
361 s). The campaign's 20 Hz small-error case otherwise (preset ``correct``, its tuning and
initial errors; radar draws from seed 2005): the EKF and the UKF of the launcher model as it is,
and of the same model with ``stage2_mass_flow`` marked estimated (initial value the model's,
sigma 10 %, constant). Whole-flight RMS (eq 11) and stage-2 RMS (361-434.3 s) of r and V, the
final errors, and the estimated factor (estimate / model value) at insertion: RMS of its error
against 1.05 over the runs and its mean 1-sigma.
"""
from __future__ import annotations

import argparse
import copy
import json

import numpy as np

from symkf.models import get_model
from symkf.models import launcher as L
from symkf.models.estimation import estimate
from symkf.runtime import estimated, load
from symkf.scenarios.launcher import campaign as C
from symkf.scenarios.launcher.truth import propagate, radar_track
from symkf.scenarios.campaign import run_rng
from symkf.scenarios.metrics import state_error

MISMATCH = 1.05        # the truth's stage-2 mass flow over the model's
PARAMETER = "stage2_mass_flow"
FILTERS = ("ekf", "ukf")


def estimating_model():
    model = copy.copy(get_model("launcher"))
    model.name, model.estimated = "launcher_est", {}
    estimate(model, PARAMETER, sigma=0.1 * L.GUIDANCE[PARAMETER], random_walk=0.0)
    return model


def table(runs: int, seed: int = 2005) -> dict:
    case, tuning = C.Case(20, "small"), C.TUNING
    measurement = L.RADAR_MEASUREMENTS[tuning["stations"]]
    times = C.flight_times(20, L.T_INSERTION)
    truth = propagate(times, {**L.GUIDANCE, PARAMETER: MISMATCH * L.GUIDANCE[PARAMETER]})
    track = radar_track(times, truth, measurement)
    x0, P0 = C.initial_estimate(case, truth[0], tuning["P0_floor"])
    stage2 = times >= L.T_STAGE2_IGNITION
    builds = {"model as is": load("launcher"), "estimated": load(estimating_model())}
    out = {}
    for label, compiled in builds.items():
        for family in FILTERS:
            Q = tuning["Q"] * tuning[f"{family}_q_scale"]
            xa, Pa, Qa = estimated.augment(compiled, x0, P0, Q)
            f = compiled.filter(family, xa, Pa, Qa, **({"kappa": tuning["kappa"]} if family == "ukf" else {}))
            squared, finals, factors, sigmas, failed = [], [], [], [], 0
            for run in range(runs):
                z = track.noisy(run_rng(seed, 20, 0, run))
                f.x, f.P = xa, Pa
                f.t = 0.0
                result = f.run(times, z, measurement, q=track.station_params())
                failed += int(np.count_nonzero(result.status))
                error = state_error(truth, result.x[:, :6], C.ANGLE_STATES)
                squared.append(error ** 2)
                finals.append(np.abs(error[-1]))
                for name, (value, sigma) in estimated.report(f).items():
                    factors.append(value / L.GUIDANCE[name])
                    sigmas.append(sigma / L.GUIDANCE[name])
            rms = np.sqrt(np.mean(squared, axis=0))
            row = {"r_rms_m": float(rms[:, 3].mean()), "V_rms_m_s": float(rms[:, 0].mean()),
                   "r_rms_stage2_m": float(rms[stage2, 3].mean()), "V_rms_stage2_m_s": float(rms[stage2, 0].mean()),
                   "r_final_m": float(np.sqrt(np.mean(np.square(finals)[:, 3]))),
                   "V_final_m_s": float(np.sqrt(np.mean(np.square(finals)[:, 0]))), "failed_steps": failed, "runs": runs}
            if factors:
                row.update(factor_error_rms=float(np.sqrt(np.mean((np.array(factors) - MISMATCH) ** 2))),
                           factor_mean=float(np.mean(factors)), factor_sigma_mean=float(np.mean(sigmas)))
            out.setdefault(family, {})[label] = row
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    result = table(args.runs)
    print(f"{'filter':6s} {'build':12s} {'r RMS':>7s} {'V RMS':>7s} {'r RMS s2':>8s} {'V RMS s2':>8s} {'r final':>8s} "
          f"{'V final':>8s} {'factor':>7s} {'its err':>8s} {'sigma':>7s}")
    for family, rows in result.items():
        for label, row in rows.items():
            est = (f"{row['factor_mean']:7.4f} {row['factor_error_rms']:8.4f} {row['factor_sigma_mean']:7.4f}"
                   if "factor_mean" in row else f"{'-':>7s} {'-':>8s} {'-':>7s}")
            print(f"{family:6s} {label:12s} {row['r_rms_m']:7.2f} {row['V_rms_m_s']:7.3f} {row['r_rms_stage2_m']:8.2f} "
                  f"{row['V_rms_stage2_m_s']:8.3f} {row['r_final_m']:8.2f} {row['V_final_m_s']:8.3f} {est}")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(result, handle, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
