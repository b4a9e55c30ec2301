"""Paper 004's radar (eq 7) with WGS84 geodetic stations, against an independent NumPy oracle
written here from the WGS84 formulas (no geodesy package), and against the spherical preset."""
import numpy as np
import pytest

from symkf.codegen.discretize import measurement_function
from symkf.models import get_model
from symkf.models import launcher as L
from symkf.scenarios.launcher.truth import propagate, radar_track, station_params

A, F = 6378137.0, 1 / 298.257223563          # WGS84 defining constants, typed again on purpose
E2 = F * (2 - F)


def ecef_from_geodetic(lat, lon, h):
    n = A / np.sqrt(1 - E2 * np.sin(lat) ** 2)
    return np.array([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1 - E2) + h) * np.sin(lat)])


def oracle(state, lat, lon, h):
    """Range, elevation, azimuth from ENU unit vectors of the ellipsoid normal at the station."""
    r, theta, phi = state[3], state[4], state[5]
    vehicle = r * np.array([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)])
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    east = np.cross([0.0, 0.0, 1.0], up)
    east /= np.linalg.norm(east)
    north = np.cross(up, east)
    d = vehicle - ecef_from_geodetic(lat, lon, h)
    e, n, u = d @ east, d @ north, d @ up
    return np.array([np.linalg.norm(d), np.arcsin(u / np.linalg.norm(d)), np.arctan2(e, n)])


@pytest.fixture(scope="module")
def h_wgs84():
    return measurement_function(get_model("launcher"), "radar_wgs84")


def _measure(h, state, q):
    return np.array(h(0.0, state, np.zeros(0), np.array(get_model("launcher").param_defaults), q)).ravel()


@pytest.mark.parametrize("t", [20.0, 131.0, 250.0, 400.0])
@pytest.mark.parametrize("station", [1, 2, 3])
def test_wgs84_radar_matches_independent_enu_oracle(h_wgs84, t, station):
    state = propagate(np.array([t]))[0]
    lat, lon, h = L.station_params_wgs84(station)
    z, expected = _measure(h_wgs84, state, [lat, lon, h]), oracle(state, lat, lon, h)
    assert abs(z[0] - expected[0]) < 1e-6                     # m
    np.testing.assert_allclose(z[1:], expected[1:], rtol=0, atol=1e-12)   # rad


def test_a_point_on_the_ellipsoid_normal_is_straight_up(h_wgs84):
    lat, lon, h = 28.8 * L.DEG, 129.5 * L.DEG, 120.0
    above = ecef_from_geodetic(lat, lon, h + 5000.0)          # 5 km along the ellipsoid normal
    r = np.linalg.norm(above)
    state = np.array([1.0, 0.0, 0.0, r, np.arctan2(above[1], above[0]), np.arcsin(above[2] / r)])
    z = _measure(h_wgs84, state, [lat, lon, h])
    assert abs(z[0] - 5000.0) < 1e-6 and abs(z[1] - np.pi / 2) < 1e-6


def test_spherical_and_wgs84_stations_differ_by_kilometres():
    """The issue's finding: reading the geodetic coordinates as spherical moves the data by km."""
    times = np.arange(0.0, 434.0, 2.0)
    truth = propagate(times)
    sphere, wgs84 = radar_track(times, truth, "radar"), radar_track(times, truth, "radar_wgs84")
    seen = sphere.clean[:, 1] > 0
    range_difference = np.abs(sphere.clean[seen, 0] - wgs84.clean[seen, 0])
    assert 1e3 < range_difference.max() < 2e4
    assert np.abs(sphere.clean[seen, 1:] - wgs84.clean[seen, 1:]).max() > 1e-3      # rad: 10x the noise
    assert station_params(wgs84.stations[:2], "radar_wgs84").shape == (2, 3)
    with pytest.raises(ValueError, match="measurement"):
        station_params([1], "radar_ecef")
