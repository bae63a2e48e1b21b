"""Output files of the recording commands: checked before any work, written atomically.

* :func:`check_output` - an output option is refused (``ConfigError``, exit code 2) when it
  names one of the command's inputs (same inode: hard links, symlinks and ``./x`` vs ``x``
  are caught), a directory where a file is wanted (or a file where a directory is wanted),
  or a place that cannot be written. Commands call it for every output option BEFORE they
  read anything, so a bad option costs nothing and never leaves a half-written file.
* :func:`atomic_path` - the output is written to a temporary file in the target directory
  and renamed over the final name only when complete, so a crash (or an error half-way)
  never leaves a truncated file under the final name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from diffpos_services.errors import ConfigError

__all__ = ["atomic_path", "check_output", "same_file"]


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """Whether ``a`` and ``b`` exist and are the same file (same device and inode)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_output(
    path: str | os.PathLike[str],
    *,
    option: str,
    inputs: Iterable[str | os.PathLike[str]] = (),
    directory: bool = False,
) -> Path:
    """Refuse an output that would overwrite an input or cannot be written.

    Parameters
    ----------
    path : path
        The output (file, or directory with ``directory=True``).
    option : str
        The option naming it (for the message), e.g. ``"--write-mcap"``.
    inputs : paths
        The command's input files; the output must not be any of them.
    directory : bool
        The output is a directory (created later if missing).

    Returns
    -------
    Path
        ``path`` as a Path.

    Raises
    ------
    ConfigError
        Names the option and what to change.
    """
    out = Path(path)
    for src in inputs:
        if same_file(out, src):
            raise ConfigError(
                f"{option} {out}: that is the input file {src}; this command never writes "
                "over its input: give a different output path"
            )
    if out.exists():
        if directory and not out.is_dir():
            raise ConfigError(f"{option} {out}: exists and is not a directory: give a directory")
        if not directory and out.is_dir():
            raise ConfigError(f"{option} {out}: is a directory: give a file name")
        target = out if directory else out.parent
    else:
        target = _nearest_existing(out.parent.resolve())
        if not target.is_dir():
            raise ConfigError(f"{option} {out}: {target} is not a directory")
    if not os.access(target, os.W_OK | os.X_OK):
        raise ConfigError(f"{option} {out}: cannot write in {target} (permission denied)")
    if not directory and out.exists() and not os.access(out, os.W_OK):
        raise ConfigError(f"{option} {out}: exists and is not writable")
    return out


@contextlib.contextmanager
def atomic_path(dst: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary path next to ``dst``, renamed to ``dst`` when the block ends normally.

    The temporary file keeps ``dst``'s suffix (writers that check it keep working) and is
    removed when the block raises. The final file gets the usual ``0o666 & ~umask`` mode.
    """
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{dst.name}.", suffix=f".partial{dst.suffix}",
                                    dir=dst.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, dst)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
