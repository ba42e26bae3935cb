"""Hypothesis settings shared by the fuzz tests.

``make test`` runs a fixed (derandomised) set of examples, so CI cannot fail on an input
it has never seen before. ``make fuzz`` sets ``GPOCC_FUZZ_EXAMPLES`` and explores fresh
random inputs; whatever it finds becomes a named regression test.
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings


def fuzz_settings(max_examples: int) -> settings:
    """``max_examples`` fixed examples, or ``$GPOCC_FUZZ_EXAMPLES`` random ones."""
    explore = os.environ.get("GPOCC_FUZZ_EXAMPLES")
    return settings(max_examples=int(explore) if explore else max_examples, deadline=None,
                    derandomize=not explore, database=None,
                    suppress_health_check=[HealthCheck.too_slow])
