"""Command-line tools (the `ptz-selfcal` entry point), thin over core and nodes."""
