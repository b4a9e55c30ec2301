"""symkf: models written once in CasADi, compiled to C, run as EKF/UKF filters.

Sub-packages: ``symkf.models`` (symbolic equations), ``symkf.codegen`` (CasADi Functions and C),
``symkf.runtime`` (compiled filters from Python), ``symkf.scenarios`` (paper reproductions, CLI).
"""
from pathlib import Path

__version__ = "0.1.0"

#: The project root when run from a source checkout (holds ``build/`` and ``results/``).
PROJECT_ROOT = Path(__file__).resolve().parent.parent
