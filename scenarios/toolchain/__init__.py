"""Benches of the toolchain itself (not of a paper): the model author's build loop and single
precision beside double, run as ``symkf bench build`` and ``symkf bench float``."""
