"""Paper experiment: attitude (truth, Monte Carlo, tables, figures, timing)."""
