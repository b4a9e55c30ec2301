"""The launcher (models/launcher.py, paper 004) with the square-root filter families beside its
EKF and UKF: the same equations, under its own name so that its build has its own folder."""
from symkf.models import launcher


def build():
    m = launcher.build()
    m.name = "launcher_sr"
    m.filters = ("ekf", "ukf", "srukf", "srekf")
    return m
