"""Subcommands of the ``socmon`` command line (see :mod:`agent.cli`)."""
