"""Values several modules share, defined once. Imports nothing: ``gpocc.entry`` reads it
before anything else is loaded.
"""

#: Occupancy classes of the class layer (uint8), ``gpocc.gp.classify.classify``'s output.
FREE, OCCUPIED, UNSURE, NO_DATA = 0, 1, 2, 255

#: Added to the diagonal of every label covariance on top of the label-noise variance:
#: keeps Cholesky stable when two samples are (numerically) the same point.
JITTER = 1e-8

#: What a Ctrl-C before any output prints (the console script and the CLI alike).
INTERRUPTED = "gpocc: interrupted before any output was written"

#: The JSON files that mark a folder as a gpocc output (``gpocc.io.atomic`` lets
#: ``--force`` replace only such folders): a map's, a simulation's, an evaluation's.
METADATA_FILE = "metadata.json"
SIMULATION_FILE = "simulation.json"
RESULTS_FILE = "results.json"
FOLDER_MARKERS = (METADATA_FILE, SIMULATION_FILE, RESULTS_FILE)
