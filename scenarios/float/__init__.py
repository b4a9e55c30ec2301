"""Single precision beside double: ``symkf bench float`` (scenarios/float/bench.py)."""
