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
