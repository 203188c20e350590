"""The `rover` command line and the registry of built-in operators: the top layer, free to import anything."""

from rover.cli.commands import main

__all__ = ["main"]
