"""The ``srl`` command's subcommands, one module each: ``NAME``, ``HELP``, ``add_arguments``, ``main``."""
