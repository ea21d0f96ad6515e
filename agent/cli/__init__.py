"""Subcommands of the ``socmon`` command line (see :mod:`agent.cli.main`).

The top layer: a command module parses its flags, calls one function of :mod:`design`
or :mod:`agent` and prints; it holds no numerics of its own.
"""
