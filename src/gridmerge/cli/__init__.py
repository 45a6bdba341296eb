"""Command-line interface of gridmerge."""
