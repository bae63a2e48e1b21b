"""The one error class of the recording package (like ``mcap.exceptions``)."""

from __future__ import annotations

from diffpos_services.errors import DiffposError

__all__ = ["ForeignRecordingError", "RecordingError"]


class RecordingError(DiffposError):
    """A recording cannot be read or written; the message says what to do about it.

    ``diffpos replay``, ``inspect`` and ``recover`` exit with 2 on it (as ``ConfigError``).
    """

    exit_code = 2


class ForeignRecordingError(RecordingError):
    """Not a diffpos recording: an empty file, a file that is not MCAP, or a valid MCAP file
    that holds no diffpos channel (nothing of ours to convert or replay).

    Exit code 1: nothing is wrong with the command, the input is just not ours.
    """

    exit_code = 1
