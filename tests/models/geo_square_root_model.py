"""The Koreasat-3 model (models/geo_satellite.py, paper 003) with the square-root continuous-discrete
EKF beside its CD-EKF: the same equations, under its own name so that its build has its own folder."""
from symkf.models import geo_satellite


def build():
    m = geo_satellite.build()
    m.name = "geo_sr"
    m.filters = ("cd_ekf", "srcdekf")
    return m
