"""``python -m gpocc`` runs the CLI."""

from gpocc.cli import main

main()
