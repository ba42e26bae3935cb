"""One module per CLI command; each only wires pipeline stages together."""
