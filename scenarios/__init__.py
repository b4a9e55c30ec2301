"""The papers' experiments: truth simulation, Monte Carlo, metrics, tables, figures, CLI.

Plain orchestration: every equation comes from ``symkf.models`` through ``symkf.codegen``.
"""
