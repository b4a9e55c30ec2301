"""Paper experiment: geo (truth, Monte Carlo, tables, figures, timing)."""
