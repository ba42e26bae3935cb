"""``python -m gpocc`` runs the CLI."""

from gpocc.entry import main

main()
