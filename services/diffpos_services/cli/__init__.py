"""The ``diffpos`` command line: one module per subcommand (``add_arguments``, ``run``).

Nothing outside this package imports it; :mod:`diffpos_services.cli.main` dispatches.
"""
