"""The one error class of the recording package (like ``mcap.exceptions``)."""

from __future__ import annotations

from diffpos_services.kit import DiffposError

__all__ = ["RecordingError"]


class RecordingError(DiffposError):
    """A recording cannot be read or written; the message says what to do about it.

    ``diffpos replay``, ``inspect`` and ``recover`` exit with 2 on it (as ``ConfigError``).
    """

    exit_code = 2
