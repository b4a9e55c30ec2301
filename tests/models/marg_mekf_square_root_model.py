"""The MARG MEKF model (models/marg_mekf.py, paper 001) with the square-root MEKF beside its MEKF:
the same equations, under its own name so that its build has its own folder."""
from symkf.models import marg_mekf


def build():
    m = marg_mekf.build()
    m.name = "marg_mekf_sr"
    m.filters = ("mekf", "srmekf")
    return m
