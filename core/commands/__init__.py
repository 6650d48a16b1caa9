"""Subcommands of the ``esgs`` CLI, one module each (see :mod:`esgs.core.cli`)."""
