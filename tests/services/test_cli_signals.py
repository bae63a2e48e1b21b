"""A stop signal that arrives while a verb's modules are still importing exits 130, like
Ctrl-C (docs/faults.md, "Signals and exit codes"); before cli/main.py installed its handlers
first, SIGTERM there killed the process (143 from a shell, -15 here) and SIGHUP too."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

#: Runs ``diffpos emulate --help`` in a fresh interpreter whose verb loading sends the signal
#: to itself first: a signal "during the imports", with no timing involved. The signal's
#: disposition is first set as a shell would leave it (``dfl``) or as ``nohup`` does (``ign``),
#: whatever the test runner inherited.
PROBE = """
import importlib, os, signal, sys
signal.signal(getattr(signal, sys.argv[1]),
              signal.SIG_DFL if sys.argv[2] == "dfl" else signal.SIG_IGN)
from diffpos_services.cli import main as cli
def load(name):
    os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    return importlib.import_module(f"diffpos_services.cli.{cli.COMMANDS[name][0]}")
cli._load = load
sys.exit(cli.main(["emulate", "--help"]))
"""


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP"])
def test_a_stop_signal_during_the_imports_exits_130(sig: str) -> None:
    out = subprocess.run([sys.executable, "-c", PROBE, sig, "dfl"], capture_output=True,
                         text=True, timeout=60, check=False)
    assert out.returncode == 130, (out.returncode, out.stderr[-400:])


def test_an_ignored_hangup_stays_ignored() -> None:
    """Under ``nohup`` (SIGHUP ignored) the verb keeps running: only a handler still at the
    default is replaced."""
    out = subprocess.run([sys.executable, "-c", PROBE, "SIGHUP", "ign"], capture_output=True,
                         text=True, timeout=60, check=False)
    assert out.returncode == 0 and "usage:" in out.stdout, (out.returncode, out.stderr[-400:])


def test_the_previous_handlers_come_back() -> None:
    """main() runs in-process (tests, scripts): it leaves the signal handlers as it found them."""
    from diffpos_services.cli import main as cli

    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGHUP)
    with pytest.raises(SystemExit):  # argparse's --help
        cli.main(["schemas", "--help"])
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGHUP)) == before
