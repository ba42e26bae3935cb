"""Where the benchmarks find the repository and the real logs: the one place for data paths.

``GPOCC_CARMEN_DIR`` overrides the folder of the CARMEN logs (default
``../shared/data/carmen`` beside the repository).
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
CARMEN = Path(os.environ.get("GPOCC_CARMEN_DIR", ROOT.parent / "shared" / "data" / "carmen"))
INTEL = CARMEN / "intel.gfs.log"
FREIBURG = CARMEN / "freiburg-079-corrected.log"
INTEL_CONFIG = CONFIGS / "carmen_intel.yaml"
FREIBURG_CONFIG = CONFIGS / "carmen_freiburg.yaml"
#: The config of each CARMEN log, by file name.
LOG_CONFIGS = {INTEL.name: INTEL_CONFIG, FREIBURG.name: FREIBURG_CONFIG}


def missing(*paths: Path) -> str | None:
    """None if every path exists, else a sentence naming the first missing one."""
    for path in paths:
        if not path.exists():
            return f"{path} not found (set GPOCC_CARMEN_DIR to the folder of the CARMEN logs)"
    return None
