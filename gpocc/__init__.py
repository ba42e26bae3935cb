"""gpocc: Gaussian-process occupancy maps from robot logs with input uncertainty."""

__version__ = "0.1.0"
