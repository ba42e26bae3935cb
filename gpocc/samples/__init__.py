"""From scans to uncertain training samples: beams, unscented transform."""
