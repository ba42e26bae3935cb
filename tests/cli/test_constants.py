"""Values defined once in gpocc.constants, and the modules that must read them there."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from gpocc import constants
from gpocc.gp.classify import classify
from gpocc.io.rasters import CLASS_BAND


def test_cli_does_not_import_the_entry_point():
    """gpocc.entry imports gpocc.cli when it runs; gpocc.cli must not import it back."""
    code = "import sys, gpocc.cli; print('gpocc.entry' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"


def test_class_codes_are_what_classify_writes_and_the_rasters_declare():
    p = np.array([0.95, 0.05, 0.5, np.nan])
    classes = classify(p, occupied=0.65, free=0.35)
    assert classes.tolist() == [constants.OCCUPIED, constants.FREE, constants.UNSURE,
                                constants.NO_DATA]
    declared = {c.value: c.name for c in CLASS_BAND.categories}
    assert declared == {constants.FREE: "free", constants.OCCUPIED: "occupied",
                        constants.UNSURE: "unsure", constants.NO_DATA: "no data"}
