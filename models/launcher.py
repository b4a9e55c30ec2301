"""KSLV-I launcher over a rotating spherical Earth, tracked by radar (paper 004).

Baek, Park, Park, Choi, Lim, Park, "Real-time trajectory estimation of space launch vehicle
using extended Kalman filter and unscented Kalman filter", J. Astron. Space Sci. 22(4), 2005.

- State, eq (4): x = [V, gamma, psi, r, theta, phi] — speed relative to the rotating Earth,
  flight-path angle, heading (from East towards North), geocentric radius, longitude, latitude.
- Forces, eq (5): F_T = T cos(alpha) - D, F_N = T sin(alpha) + L, bank sigma = 0.
- Dynamics, eq (6) (Vinh 1981), omega = 7.292115e-5 rad/s, inverse-square gravity.
- Radar, eq (7): range R, elevation E, azimuth A (from North, clockwise) from a station.

Choices the paper leaves open (documented, each a named constant below):

- Earth: a sphere of radius R_EARTH = 6378.137 km for the vehicle (gravity, altitude; the
  paper's r = 6678.137 km "corresponds to 300 km altitude", which fixes this radius).
- Radar stations, two measurements: ``radar`` (the paper preset) places section 3.2's station
  latitudes on that sphere, "up" radial; ``radar_wgs84`` reads them as WGS84 geodetic latitude,
  longitude and height (heights not printed: 0 m) and computes range, elevation and azimuth in
  the station's local East-North-Up frame of the ellipsoid, the vehicle's position from the
  state's geocentric (r, theta, phi). A spherical station sits 6.5-7 km above the ellipsoid
  and ~20 km south of the WGS84 one (geocentric vs geodetic latitude), so the two differ along
  this flight by up to 17 km in range and 0.09 rad in elevation (hundreds of times the noise).
- Atmosphere: exponential, rho = 1.225 exp(-h / 7.2 km); speed of sound 340 m/s; drag
  coefficient Cd(M) = 0.25 + 0.25 / (1 + ((M - 1.1)/0.4)^2) (transonic peak 0.5); lift slope
  CL_alpha = 2 /rad; reference area from the stage diameter of Table 1.
- Table 1 is not self-consistent: the printed thrusts (178.0 tf, 12.1 tf) disagree with
  Isp x g0 x flow (155.0 tf, 10.8 tf); stage 2's 36.8 kg/s over 79.3 s is 2.92 t, not 2.1 t,
  and Table 2 burns it for 73.3 s (361.0-434.3 s). We take thrust = Isp g0 mdot with Table 1's
  Isp (both stages) and stage-1 flow (625.2 kg/s x 131.0 s = 81.9 t, consistent), because with
  178.0 tf the stage-1 burnout speed is about 5.7 km/s at Table 2's 78.8 km instead of 4.68;
  the stage-2 flow is *solved* with the guidance so the burnout meets the insertion conditions
  over Table 2's burn window (the solved value is in GUIDANCE; Table 1 says 36.8 kg/s).
- Guidance (not given in the paper): lift-off with initial flight-path angle gamma_0 <= 86 deg
  (a pitch kick; the state's heading psi is singular at gamma = 90 deg, where Vinh's equations
  divide by cos(gamma), so a near-vertical start makes psi unobservable and lets estimates cross
  90 deg), then angle of attack alpha(t) = a0 + a1 (t/t1)^2 + a2 (t/t1) in stage 1,
  zero in the coast, and alpha(t) = b0 + b1 (t - t_ign) in stage 2 (linear steering). The
  numbers are solved with IPOPT by ``symkf.scenarios.launcher.guidance`` to meet Table 2;
  its output is pasted into GUIDANCE below.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from .base import Model

# ---------------------------------------------------------------- physical constants
G0 = 9.80665                      # m/s^2, standard gravity (tonne-force -> N)
MU_EARTH = 3.986004418e14         # m^3/s^2, WGS-84 GM
R_EARTH = 6378.137e3              # m, sphere radius (paper: r = 6678.137 km <-> 300 km altitude)
OMEGA_EARTH = 7.292115e-5         # rad/s, paper 004 after eq (6)
DEG = np.pi / 180.0
WGS84_A = 6378137.0               # m, WGS84 semi-major axis
WGS84_F = 1 / 298.257223563       # WGS84 flattening
WGS84_E2 = WGS84_F * (2 - WGS84_F)  # first eccentricity squared

# ---------------------------------------------------------------- Table 1: vehicle
STAGE1_MASS = 87.2e3              # kg, Table 1 total mass, stage 1
STAGE1_PROPELLANT = 81.9e3        # kg, Table 1
STAGE1_THRUST_TABLE = 178.0e3 * G0  # N, Table 1 (178.0 tonne-force; not used, see docstring)
STAGE1_FLOW = 625.2               # kg/s, Table 1
STAGE1_ISP = 248.0                # s, Table 1
STAGE1_THRUST = STAGE1_ISP * G0 * STAGE1_FLOW   # N: 1.52 MN = 155.0 tf
STAGE1_DIAMETER = 2.4             # m, Table 1
STAGE2_MASS = 3.4e3               # kg, Table 1
STAGE2_PROPELLANT = 2.1e3         # kg, Table 1 (not used: see module docstring)
STAGE2_THRUST_TABLE = 12.1e3 * G0  # N, Table 1 (12.1 tonne-force; not used, see docstring)
STAGE2_ISP = 292.3                # s, Table 1; thrust = STAGE2_ISP * G0 * (solved flow)
STAGE2_FLOW_TABLE = 36.8          # kg/s, Table 1 (replaced by the solved GUIDANCE value)
STAGE2_DIAMETER = 1.27            # m, Table 1
PAYLOAD_MASS = 0.11e3             # kg, Table 1
FAIRING_MASS = 0.1e3              # kg, Table 1
LIFTOFF_MASS = STAGE1_MASS + STAGE2_MASS + PAYLOAD_MASS + FAIRING_MASS

# ---------------------------------------------------------------- Table 2: flight events (s)
T_STAGE1_BURNOUT = 131.0          # Table 2: 1st-stage separation
T_FAIRING = 153.9                 # Table 2: fairing jettison
T_STAGE2_IGNITION = 361.0         # Table 2: 2nd-stage ignition
T_INSERTION = 434.3               # Table 2: 2nd-stage separation / perigee insertion

#: Table 2 rows: (time s, event, altitude km, speed km/s).
FLIGHT_EVENTS = (
    (0.0, "lift-off", 0.0, 0.02),
    (131.0, "stage-1 separation", 78.8, 4.68),
    (153.9, "fairing jettison", 115.4, 4.60),
    (361.0, "stage-2 ignition", 285.4, 4.23),
    (434.3, "perigee insertion", 300.0, 8.04),
)
#: Boundary conditions at insertion (section 3.1): r, gamma, V.
INSERTION_RADIUS = 6678.137e3     # m
INSERTION_FLIGHT_PATH_ANGLE = 0.0  # rad
INSERTION_SPEED = 8.038e3         # m/s

# ---------------------------------------------------------------- atmosphere (our choice)
RHO_SEA_LEVEL = 1.225             # kg/m^3
SCALE_HEIGHT = 7.2e3              # m
SPEED_OF_SOUND = 340.0            # m/s
LIFT_SLOPE = 2.0                  # 1/rad

# ---------------------------------------------------------------- launch site and radars
#: Naro Space Center (not printed in the paper; public coordinates), rad.
LAUNCH_LATITUDE = 34.4316 * DEG
LAUNCH_LONGITUDE = 127.5352 * DEG
#: Heading at lift-off, from East towards North: -80 deg is a course of 170 deg (south by east),
#: toward the paper's down-range stations 2 and 3.
LAUNCH_HEADING = -80.0 * DEG
LIFTOFF_SPEED = 20.0              # m/s, Table 2 (0.02 km/s at t = 0)

#: Section 3.2: radar stations (geodetic latitude, longitude) in degrees, and tracking windows.
RADAR_STATIONS_DEG = ((33.8, 126.8), (28.8, 129.5), (24.5, 125.4))
RADAR_HANDOVER_TIMES = (178.0, 311.8)           # s: station 1 -> 2, station 2 -> 3
RADAR_SIGMA = (10.0, 0.1e-3, 0.1e-3)            # m, rad, rad: section 3.2
#: Station heights above the WGS84 ellipsoid (m): not printed in the paper, taken as 0.
RADAR_STATION_HEIGHTS_M = (0.0, 0.0, 0.0)
#: The measurement of each station model (the spherical one is the paper preset).
RADAR_MEASUREMENTS = {"spherical": "radar", "wgs84": "radar_wgs84"}

#: Scales of the scaled state (our choice, codegen/scaling.py; rounded to powers of two): about the
#: radar-converged 1-sigma of each state, angles of position in ~1 m on the ground (1 / R_EARTH).
STATE_SCALE = {"V": 0.03, "gamma": 1e-5, "psi": 1e-5, "r": 1.0, "theta": 1.0 / R_EARTH, "phi": 1.0 / R_EARTH}
#: Section 4, eq (9) and (10): initial estimation errors dx0 = x - x_hat (small and large).
INITIAL_ERROR = {
    "small": (0.001, 1e-12, 1e-12, 0.0, 0.0, 0.0),          # eq (9): m/s, rad, rad, m, rad, rad
    "large": (10.0, 1e-8, 1e-8, 1000.0, 1e-8, 1e-8),         # eq (10)
}
RADAR_RATES_HZ = (20, 10)                                    # section 4: radar data rates

#: Table 3: whole-flight RMS error (eq 11) per state, (EKF, UKF) per case; units m/s, deg, deg,
#: m, deg, deg. Keys: (rate Hz, "small"|"large").
TABLE3_UNITS = ("m/s", "deg", "deg", "m", "deg", "deg")
TABLE3 = {
    (20, "small"): {"V": (0.029, 0.024), "gamma": (9.74e-3, 3.66e-3), "psi": (1.68e-2, 6.59e-4),
                    "r": (0.575, 0.535), "theta": (6.07e-6, 6.02e-6), "phi": (5.42e-6, 4.84e-6)},
    (20, "large"): {"V": (0.074, 0.045), "gamma": (3.84e-2, 4.30e-3), "psi": (5.55e-3, 1.08e-3),
                    "r": (0.999, 0.691), "theta": (6.65e-6, 6.07e-6), "phi": (9.45e-6, 4.90e-6)},
    (10, "small"): {"V": (0.643, 0.142), "gamma": (1.42e-2, 5.68e-3), "psi": (2.71e-3, 6.76e-4),
                    "r": (18.900, 0.990), "theta": (1.15e-4, 9.00e-6), "phi": (3.85e-4, 1.63e-5)},
    (10, "large"): {"V": (0.711, 0.166), "gamma": (5.09e-2, 7.91e-3), "psi": (8.19e-3, 1.43e-3),
                    "r": (19.900, 1.24), "theta": (1.19e-4, 9.22e-6), "phi": (3.95e-4, 1.62e-5)},
}
#: Section 4: processing time per step, MATLAB 6.5 on an Athlon XP 2500+ (ms).
PAPER_MS_PER_STEP = {"ekf": 2.32, "ukf": 9.22}

#: Guidance and stage-2 flow solved by ``symkf.scenarios.launcher.guidance`` (IPOPT) to meet
#: Table 2 and the insertion conditions. Regenerate with ``symkf design-guidance``.
GUIDANCE = {
    "initial_flight_path_angle": 1.5009831716994506,   # rad (86.0 deg, the design bound)
    "stage1_alpha_0": 0.04151953872928711,              # rad
    "stage1_alpha_quadratic": 0.3310328204616789,       # rad
    "stage1_alpha_linear": -0.34906585383018535,        # rad
    "stage2_alpha_0": 0.1481464908231482,               # rad
    "stage2_alpha_rate": -0.003490658531949411,         # rad/s
    "stage2_mass_flow": 34.85829296568308,              # kg/s (Table 1: 36.8)
}
GUIDANCE_PARAMS = ("stage1_alpha_0", "stage1_alpha_quadratic", "stage1_alpha_linear", "stage2_alpha_0",
                   "stage2_alpha_rate", "stage2_mass_flow")


def station_params(station: int) -> np.ndarray:
    """Measurement parameters [latitude, longitude] (rad) of radar station 1, 2 or 3."""
    lat, lon = RADAR_STATIONS_DEG[station - 1]
    return np.array([lat * DEG, lon * DEG])


def station_params_wgs84(station: int) -> np.ndarray:
    """Measurement parameters [geodetic latitude (rad), longitude (rad), height (m)] of station 1-3."""
    lat, lon = RADAR_STATIONS_DEG[station - 1]
    return np.array([lat * DEG, lon * DEG, RADAR_STATION_HEIGHTS_M[station - 1]])


def station_at(t: float) -> int:
    """The tracking station (1, 2 or 3) at time t, section 3.2's hand-over schedule."""
    return 1 + sum(t >= handover for handover in RADAR_HANDOVER_TIMES)


def initial_state(guidance: dict | None = None) -> np.ndarray:
    """The true state at lift-off: Table 2 speed, the solved pitch kick, the launch site."""
    g = GUIDANCE if guidance is None else guidance
    return np.array([LIFTOFF_SPEED, g["initial_flight_path_angle"], LAUNCH_HEADING,
                     R_EARTH, LAUNCH_LONGITUDE, LAUNCH_LATITUDE])


def inertial_speed(x):
    """Speed in the non-rotating frame: the relative velocity of eq (4)'s (V, gamma, psi) in local
    East-North-Up plus the Earth's rotation, omega r cos(phi) towards East (the paper's 8.038 km/s
    boundary value is quoted as the orbital, i.e. inertial, perigee speed)."""
    V, gamma, psi, r, phi = x[0], x[1], x[2], x[3], x[5]
    east = V * ca.cos(gamma) * ca.cos(psi) + OMEGA_EARTH * r * ca.cos(phi)
    north = V * ca.cos(gamma) * ca.sin(psi)
    up = V * ca.sin(gamma)
    return ca.sqrt(east**2 + north**2 + up**2)


def _step(t, t0):
    """1 for t >= t0, else 0 (event switches of the thrust and mass schedule)."""
    return ca.if_else(t >= t0, 1.0, 0.0)


def _propulsion(t, stage2_mass_flow):
    """Thrust (N), mass (kg) and reference area (m^2) against time: Tables 1 and 2."""
    stage1_on = 1 - _step(t, T_STAGE1_BURNOUT)
    stage2_on = _step(t, T_STAGE2_IGNITION) * (1 - _step(t, T_INSERTION))
    thrust = stage1_on * STAGE1_THRUST + stage2_on * STAGE2_ISP * G0 * stage2_mass_flow
    upper_mass = STAGE2_MASS + PAYLOAD_MASS + FAIRING_MASS * (1 - _step(t, T_FAIRING))
    burned2 = stage2_mass_flow * (ca.fmin(ca.fmax(t, T_STAGE2_IGNITION), T_INSERTION) - T_STAGE2_IGNITION)
    mass = stage1_on * (LIFTOFF_MASS - STAGE1_FLOW * t) + (1 - stage1_on) * (upper_mass - burned2)
    diameter = stage1_on * STAGE1_DIAMETER + (1 - stage1_on) * STAGE2_DIAMETER
    return thrust, mass, np.pi / 4 * diameter**2


def _angle_of_attack(t, a0, a1, a2, b0, b1):
    """The guidance law (our design, module docstring): alpha(t) in rad."""
    tau = t / T_STAGE1_BURNOUT
    stage1 = (1 - _step(t, T_STAGE1_BURNOUT)) * (a0 + a1 * tau**2 + a2 * tau)
    stage2 = _step(t, T_STAGE2_IGNITION) * (b0 + b1 * (t - T_STAGE2_IGNITION))
    return stage1 + stage2


def _aerodynamics(V, r, alpha, area):
    """Drag and lift (N): exponential atmosphere, Mach-dependent Cd (module docstring)."""
    altitude = r - R_EARTH
    rho = RHO_SEA_LEVEL * ca.exp(-altitude / SCALE_HEIGHT)
    mach = V / SPEED_OF_SOUND
    drag_coefficient = 0.25 + 0.25 / (1 + ((mach - 1.1) / 0.4) ** 2)
    dynamic_pressure = 0.5 * rho * V**2
    return dynamic_pressure * drag_coefficient * area, dynamic_pressure * LIFT_SLOPE * alpha * area


def build() -> Model:
    """The launcher model: dynamics eq (6) with forces eq (5), radar eq (7)."""
    m = Model("launcher", "KSLV-I launcher over a rotating Earth, three tracking radars",
              paper="Baek et al. 2005, J. Astron. Space Sci. 22(4) (paper 004)")
    # scale ~ the estimate's uncertainty, offset ~ where the state lives (the scaled state of a float
    # build, codegen/scaling.py): longitude and latitude in units of ~1 m on the ground
    V = m.state("V", "m/s", "speed relative to the rotating Earth", scale=STATE_SCALE["V"])
    gamma = m.state("gamma", "rad", "flight-path angle above the local horizontal", scale=STATE_SCALE["gamma"])
    psi = m.state("psi", "rad", "heading, from East towards North", scale=STATE_SCALE["psi"], offset=LAUNCH_HEADING)
    r = m.state("r", "m", "distance from the Earth's centre", scale=STATE_SCALE["r"], offset=R_EARTH)
    theta = m.state("theta", "rad", "longitude", scale=STATE_SCALE["theta"], offset=LAUNCH_LONGITUDE)
    phi = m.state("phi", "rad", "geocentric latitude", scale=STATE_SCALE["phi"], offset=LAUNCH_LATITUDE)
    a0, a1, a2, b0, b1, flow2 = (m.param(name, unit, desc, GUIDANCE[name]) for name, unit, desc in (
        ("stage1_alpha_0", "rad", "stage-1 angle of attack at lift-off"),
        ("stage1_alpha_quadratic", "rad", "stage-1 angle of attack, coefficient of (t/t1)^2"),
        ("stage1_alpha_linear", "rad", "stage-1 angle of attack, coefficient of t/t1"),
        ("stage2_alpha_0", "rad", "stage-2 angle of attack at ignition"),
        ("stage2_alpha_rate", "rad/s", "stage-2 angle-of-attack rate"),
        ("stage2_mass_flow", "kg/s", "stage-2 mass flow (solved, see docstring)")))
    t = m.t

    thrust, mass, area = _propulsion(t, flow2)
    alpha = _angle_of_attack(t, a0, a1, a2, b0, b1)
    drag, lift = _aerodynamics(V, r, alpha, area)
    force_tangential = thrust * ca.cos(alpha) - drag          # eq (5)
    force_normal = thrust * ca.sin(alpha) + lift              # eq (5)
    bank = 0.0                                                # sigma: planar guidance
    g = MU_EARTH / r**2
    w = OMEGA_EARTH
    sg, cg, sp, cp, sf, cf = ca.sin(gamma), ca.cos(gamma), ca.sin(psi), ca.cos(psi), ca.sin(phi), ca.cos(phi)

    # eq (6), term by term as printed
    dV = force_tangential / mass - g * sg + w**2 * r * cf * (sg * cf - cg * sp * sf)
    dgamma = (force_normal * np.cos(bank) / mass - g * cg + V**2 / r * cg + 2 * w * V * cp * cf
              + w**2 * r * cf * (cg * cf + sg * sp * sf)) / V
    dpsi = (force_normal * np.sin(bank) / (mass * cg) - V**2 / r * cg * cp * sf / cf
            + 2 * w * V * (sg / cg * sp * cf - sf) - w**2 * r / cg * cp * sf * cf) / V
    m.set_dynamics({"V": dV, "gamma": dgamma, "psi": dpsi, "r": V * sg,
                    "theta": V * cg * cp / (r * cf), "phi": V * cg * sp / r})

    station_lat, station_lon = m.measurement_params("radar", [
        ("station_latitude", "rad", "radar station latitude (on the spherical Earth)"),
        ("station_longitude", "rad", "radar station longitude")])
    station = _on_sphere(R_EARTH, station_lat, station_lon)
    rng, elevation, azimuth = _radar(_on_sphere(r, phi, theta), station, station_lat, station_lon)
    m.measurement("radar", [
        ("range", "m", "slant range from the station, eq (7)", rng),
        ("elevation", "rad", "elevation above the station's horizontal, eq (7)", elevation),
        ("azimuth", "rad", "azimuth from North, clockwise, eq (7)", azimuth)],
        sigma=RADAR_SIGMA, wrap=(False, False, True))

    geo_lat, geo_lon, geo_height = m.measurement_params("radar_wgs84", [
        ("station_latitude", "rad", "radar station geodetic latitude (WGS84)"),
        ("station_longitude", "rad", "radar station longitude (WGS84)"),
        ("station_height", "m", "radar station height above the WGS84 ellipsoid")])
    station = geodetic_to_ecef(geo_lat, geo_lon, geo_height)
    rng, elevation, azimuth = _radar(_on_sphere(r, phi, theta), station, geo_lat, geo_lon)
    m.measurement("radar_wgs84", [
        ("range", "m", "slant range from a WGS84 station, eq (7)", rng),
        ("elevation", "rad", "elevation above the station's ellipsoid tangent plane, eq (7)", elevation),
        ("azimuth", "rad", "azimuth from geodetic North, clockwise, eq (7)", azimuth)],
        sigma=RADAR_SIGMA, wrap=(False, False, True))
    # Table 2's switches of thrust, mass and area: no integrator step straddles one
    m.events = (T_STAGE1_BURNOUT, T_FAIRING, T_STAGE2_IGNITION, T_INSERTION)
    # -O1: measured (callgrind, gcc 12) 2-4 % more instructions per EKF/UKF predict than -O3, for
    # half the compile time of -O2/-O3 (the model author's edit -> loaded filter loop).
    # -O3 for the glue a dynamics edit does not recompile (the API unit, the filter kernels, the event
    # dispatchers of f_d): 1,200 fewer instructions per EKF step, 800 per UKF step, the same
    # numbers (IEEE semantics, -std=c99 keeps floating-point contraction off). -fno-thread-jumps for the
    # model's functions: GCC's jump threading copies CasADi's "arg ? arg[k] : 0" loads, and sin and cos
    # of one copy each are then not merged into one sincos call (250 instructions per step; the kernels
    # do better with it: -fthread-jumps, also written out so that the bundle's Makefile, which appends
    # a unit's own flags to the default ones, compiles them as the library does).
    m.codegen_defaults = {"rk4_substeps": 1, "optimization": "-O1 -fno-math-errno -fno-thread-jumps",
                          "unit_optimization": {pattern: "-O3 -fno-math-errno -fthread-jumps" for pattern in GLUE_UNITS}}
    return m


#: C units compiled at -O3 (codegen option ``unit_optimization``): the public API, the EKF/UKF kernels
#: and the small functions that pick an event branch of f_d (their text does not change when f or h
#: is edited: the model author's edit loop, still compiles f_d's own units at -O1).
GLUE_UNITS = ("*_api.c", "*_k_ekf_*.c", "*_k_ukf_*.c", "*_fn_fd_and_jac.c", "*_fn_fd_and_jac_plain.c",
              "*_fn_fd_and_jac_branch.c", "*_fn_fd_and_jac_split.c", "*_fn_fd_sigma.c", "*_fn_fd_sigma_branch.c")


def _on_sphere(radius, lat, lon):
    """Earth-fixed Cartesian position of a point at a geocentric radius, latitude and longitude."""
    return ca.vertcat(radius * ca.cos(lat) * ca.cos(lon), radius * ca.cos(lat) * ca.sin(lon), radius * ca.sin(lat))


def geodetic_to_ecef(lat, lon, height):
    """WGS84 geodetic latitude, longitude (rad) and ellipsoidal height (m) -> Earth-fixed x, y, z (m)."""
    n = WGS84_A / ca.sqrt(1 - WGS84_E2 * ca.sin(lat) ** 2)        # prime-vertical radius of curvature
    return ca.vertcat((n + height) * ca.cos(lat) * ca.cos(lon), (n + height) * ca.cos(lat) * ca.sin(lon),
                      (n * (1 - WGS84_E2) + height) * ca.sin(lat))


def _radar(vehicle, station, lat, lon):
    """Range, elevation and azimuth of the vehicle (Earth-fixed position) from a station whose
    local vertical has latitude ``lat`` and longitude ``lon`` (East-North-Up frame), eq (7)."""
    los = vehicle - station
    slat, clat, slon, clon = ca.sin(lat), ca.cos(lat), ca.sin(lon), ca.cos(lon)
    east = -slon * los[0] + clon * los[1]
    north = -slat * clon * los[0] - slat * slon * los[1] + clat * los[2]
    up = clat * clon * los[0] + clat * slon * los[1] + slat * los[2]
    horizontal = ca.sqrt(east**2 + north**2)
    return ca.sqrt(east**2 + north**2 + up**2), ca.atan2(up, horizontal), ca.atan2(east, north)
