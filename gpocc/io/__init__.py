"""Readers and writers: bags, CARMEN logs, rasters, map_server files."""
