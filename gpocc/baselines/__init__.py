"""Baselines the GP maps are scored against (the classic log-odds occupancy grid)."""
