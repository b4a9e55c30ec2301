"""A low-Earth-orbit orbit-determination model, written as a user would (no scales, no offsets).

States: ECI position r = (x, y, z) and velocity v (6). Dynamics: two-body gravity plus the J2
zonal term (Vallado, Fundamentals of Astrodynamics, 4th ed., eq. 8-30), with process noise w on
the three accelerations (``Model.noise``: white, power spectral density Q in (m/s^2)^2 s).
One ground station on the rotating Earth (a sphere of radius RE; Earth-fixed and inertial frames
aligned at t = 0, rotation OMEGA_E about z) measures range, range rate, azimuth (from north,
towards east) and elevation of the satellite, through the model's time symbol ``m.t``.

The truth simulation and a pass over the station: :func:`initial_orbit`, :func:`simulate`.
"""
import casadi as ca
import numpy as np

from symkf.models import Model

MU = 3.986004418e14          # m^3/s^2, Earth's gravitational parameter (WGS 84)
RE = 6378137.0               # m, Earth's equatorial radius (WGS 84)
J2 = 1.08262668e-3           # -, Earth's second zonal harmonic (EGM96)
OMEGA_E = 7.2921159e-5       # rad/s, Earth's rotation rate
STATION_LAT = 0.6981317      # rad, 40 deg N
STATION_LON = -1.8325957     # rad, 105 deg W
STATION_ALT = 1600.0         # m above the sphere
ALTITUDE = 500e3             # m, the orbit's altitude (circular)
SIGMA = (10.0, 0.05, 1e-3, 1e-3)     # m, m/s, rad, rad: range, range rate, azimuth, elevation


def station_ecef() -> np.ndarray:
    c = np.cos(STATION_LAT)
    return (RE + STATION_ALT) * np.array([c * np.cos(STATION_LON), c * np.sin(STATION_LON), np.sin(STATION_LAT)])


def enu_axes() -> np.ndarray:
    """Rows: east, north, up at the station (Earth-fixed)."""
    sl, cl, sp, cp = np.sin(STATION_LON), np.cos(STATION_LON), np.sin(STATION_LAT), np.cos(STATION_LAT)
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def build():
    m = Model("leo_od", "LEO orbit determination: ECI position and velocity, J2, one rotating ground station",
              paper="none")
    r = ca.vertcat(*[m.state(a, "m", f"ECI position {a}") for a in ("x", "y", "z")])
    v = ca.vertcat(*[m.state(f"v{a}", "m/s", f"ECI velocity {a}") for a in ("x", "y", "z")])
    w = ca.vertcat(*[m.noise(f"a{a}", "m/s^2", f"unmodelled acceleration {a}") for a in ("x", "y", "z")])
    rn = ca.norm_2(r)
    k = 1.5 * J2 * MU * RE**2 / rn**5
    zz = 5 * r[2] ** 2 / rn**2
    acc = -MU / rn**3 * r + k * ca.vertcat(r[0] * (zz - 1), r[1] * (zz - 1), r[2] * (zz - 3)) + w
    m.set_dynamics({"x": v[0], "y": v[1], "z": v[2], "vx": acc[0], "vy": acc[1], "vz": acc[2]})
    theta = OMEGA_E * m.t
    c, s = ca.cos(theta), ca.sin(theta)
    rot = ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))    # Earth-fixed -> ECI
    r_s = rot @ ca.DM(station_ecef())
    rho = r - r_s
    rho_dot = v - ca.cross(ca.DM([0, 0, OMEGA_E]), r_s)
    rng = ca.norm_2(rho)
    local = ca.DM(enu_axes()) @ (rot.T @ rho)
    m.measurement("tracking", [
        ("range", "m", "station-satellite distance", rng),
        ("range_rate", "m/s", "rate of the distance", ca.dot(rho, rho_dot) / rng),
        ("azimuth", "rad", "azimuth from north, towards east", ca.atan2(local[0], local[1])),
        ("elevation", "rad", "elevation above the horizon", ca.atan2(local[2], ca.sqrt(local[0]**2 + local[1]**2))),
    ], sigma=SIGMA, wrap=(False, False, True, False))
    m.filters = ("ekf", "ukf", "srukf", "srekf")
    return m


def initial_orbit(lead: float = 300.0, cross_track: float = 0.08) -> np.ndarray:
    """A circular orbit at ALTITUDE whose closest approach to the station is ``lead`` seconds after
    t = 0, ``cross_track`` rad (geocentric) to the side (0.08: a pass peaking near 45 deg elevation)."""
    radius = RE + ALTITUDE
    speed = np.sqrt(MU / radius)
    theta = OMEGA_E * lead
    rot = np.array([[np.cos(theta), -np.sin(theta), 0], [np.sin(theta), np.cos(theta), 0], [0, 0, 1]])
    heading = rot @ (np.cos(0.7) * enu_axes()[0] + np.sin(0.7) * enu_axes()[1])      # towards the north-east
    side = np.cross(heading, rot @ enu_axes()[2])
    up = np.cos(cross_track) * (rot @ enu_axes()[2]) + np.sin(cross_track) * side
    angle = -speed / radius * lead
    r0 = radius * (np.cos(angle) * up + np.sin(angle) * heading)
    v0 = speed * (-np.sin(angle) * up + np.cos(angle) * heading)
    return np.r_[r0, v0]


def simulate(fd, h, x0, dt: float, n_steps: int, rng, substeps: int = 10, min_elevation: float = 0.0):
    """Truth states and noisy measurements at t_k = k dt (k = 1..n_steps), the model's own f_d
    (``fd(t, dt, x)``) and h (``h(t, x)``) evaluated on finer steps; a mask of 0 where the
    satellite is below ``min_elevation`` (rad)."""
    x, truth, z, mask = np.array(x0, float), [], [], []
    for k in range(n_steps):
        for j in range(substeps):
            x = fd(k * dt + j * dt / substeps, dt / substeps, x)
        t = (k + 1) * dt
        zk = h(t, x)
        truth.append(x.copy())
        z.append(zk + rng.normal(0.0, SIGMA))
        mask.append(np.full(4, 1.0 if zk[3] > min_elevation else 0.0))
    return np.array(truth), np.array(z), np.array(mask)


def bench_case(rng, n_steps: int = 2161, dt: float = 1.0) -> dict:
    """The record of ``symkf bench float --model`` (scenarios/toolchain/square_root_float.py): one
    pass (the station sees the satellite above 5 deg for 10 minutes), then 26 minutes of prediction
    only; initial errors of 1 km and 1 m/s (1 sigma), process noise 1e-8 (m/s^2)^2 s."""
    from symkf.runtime.reference import ReferenceFilter
    P0 = np.diag([1000.0] * 3 + [1.0] * 3) ** 2
    x_true = initial_orbit()
    x0 = x_true + rng.normal(0.0, np.sqrt(np.diag(P0)))
    ref = ReferenceFilter(__file__, "ekf", x0, P0, np.eye(3))
    truth, z, mask = simulate(lambda t, d, x: ref._fd(t, d, x), lambda t, x: ref._h("tracking", t, x, np.zeros(0)),
                              x_true, dt, n_steps - 1, rng, substeps=4, min_elevation=np.radians(5.0))
    return {"x0": x0, "P0": P0, "Q": np.eye(3) * 1e-8, "times": dt * np.arange(n_steps), "measurement": "tracking",
            "z": np.vstack([z[:1], z]), "mask": np.vstack([np.zeros((1, 4)), mask]),
            "truth": np.vstack([x_true, truth])}
