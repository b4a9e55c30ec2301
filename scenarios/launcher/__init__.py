"""Paper experiment: launcher (truth, Monte Carlo, tables, figures, timing)."""
