"""The star-tracker/gyro attitude model (models/attitude.py, paper 000) with the square-root MEKF
beside its MEKF: the same equations, under its own name so that its build has its own folder."""
from symkf.models import attitude


def build():
    m = attitude.build()
    m.name = "attitude_sr"
    m.filters = ("mekf", "srmekf")
    return m
