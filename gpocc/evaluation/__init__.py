"""Scoring maps and the baselines they are scored against: ROC, grid, simulation, split."""
