"""Sampling a trained model on a raster: blocks, executors, rendering."""
