"""Shared fixtures: the compiled launcher (built once per session, into a temporary build dir)."""
import os

import pytest


@pytest.fixture(scope="session", autouse=True)
def _isolated_build_dir(tmp_path_factory):
    """Tests build into their own folder unless SYMKF_BUILD_DIR is set (CI reuses nothing stale)."""
    if "SYMKF_BUILD_DIR" not in os.environ:
        os.environ["SYMKF_BUILD_DIR"] = str(tmp_path_factory.mktemp("build"))
    yield


@pytest.fixture(scope="session")
def launcher_compiled():
    from symkf.runtime import load
    return load("launcher", backend="compiled")


@pytest.fixture(scope="session")
def launcher_bundle():
    from symkf.codegen import generate
    return generate("launcher")


TINY_MODEL = '''"""A user's model outside the symkf package: a cart with linear drag, position measured."""
import casadi as ca

from symkf.models import Model

DRAG = {drag}


def build():
    m = Model("{name}", "cart with linear drag", paper="none")
    pos = m.state("pos", "m", "position")
    vel = m.state("vel", "m/s", "velocity")
    m.set_dynamics({{"pos": vel, "vel": -DRAG * vel}})
    m.measurement("gps", [("pos", "m", "measured position", pos)], sigma=[1.0])
    m.filters = ("ekf",)
    return m
'''


@pytest.fixture
def write_model():
    """``write_model(path, drag=0.1, name="tiny")`` writes a small user model file and returns its path."""
    def write(path, drag: float = 0.1, name: str = "tiny"):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(TINY_MODEL.format(drag=drag, name=name))
        return path
    return write
