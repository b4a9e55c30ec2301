"""The package list, found rather than written by hand: ``symkf`` itself (``package/``: its version
and docstring), and every folder with an ``__init__.py`` under the four rooms (models/, codegen/,
runtime/, scenarios/) is a ``symkf.<room>...`` package, so a new
experiment folder ships in a regular install without touching pyproject.toml. The rest of the
configuration (the rooms' ``package-dir`` mapping, package data) is in pyproject.toml."""
from setuptools import find_packages, setup

ROOMS = ("models", "codegen", "runtime", "scenarios")


def room_packages() -> list[str]:
    """``symkf.<room>`` and its sub-packages, for each room (setuptools' discovery cannot add the
    ``symkf.`` prefix that the ``package-dir`` mapping gives the folders)."""
    return [package for room in ROOMS
            for package in [f"symkf.{room}", *(f"symkf.{room}.{name}" for name in find_packages(where=room))]]


setup(packages=["symkf", *room_packages()])
