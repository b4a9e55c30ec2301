"""Paper experiment: marg (truth, Monte Carlo, tables, figures, timing)."""
