"""The ``dragd`` command line: one subcommand per job (``dragd --help``); ``main`` is the entry point."""

from dragd.cli.app import main

__all__ = ["main"]
