"""Subcommands of the yauyau console script."""
