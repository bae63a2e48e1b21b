"""The one base of the errors a person sees, and its exit code.

:class:`DiffposError`'s ``exit_code`` is what the CLI returns (mapped in one place,
:func:`diffpos_services.cli.main.main`); every error class of ``diffpos_services`` derives
from it (``tests/test_import_rules.py`` checks).
"""

from __future__ import annotations

__all__ = ["ConfigError", "DiffposError"]


class DiffposError(Exception):
    """Base of every error diffpos reports to a person: the message says what to fix.

    ``exit_code`` is the process exit code the CLI returns for it (one place:
    :func:`diffpos_services.cli.main.main`); subclasses set their own.
    """

    exit_code: int = 1


class ConfigError(DiffposError, ValueError):
    """Invalid service configuration; the message names the field and what to fix."""

    exit_code = 2
