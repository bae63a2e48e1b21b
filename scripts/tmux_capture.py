"""What ``diffpos emulate`` looks like in an 80x24 terminal: run it in a detached tmux session
of that size and save the screen plus scrollback (``tmux capture-pane``) as text.

Needs tmux (``apt-get install -y tmux``) and ``diffpos`` next to this Python (the venv).

usage:
  python scripts/tmux_capture.py                         -> docs/img/terminal.txt
  python scripts/tmux_capture.py --out /tmp/x.txt -- --duration 5 --channel ideal
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DIFFPOS = Path(sys.executable).with_name("diffpos")
#: the emulate command captured (no recording left behind; everything else as a user runs it)
DEFAULT_ARGS = ["--duration", "10", "--record", "off", "--dashboard", "off"]


def tmux(*args: str, check: bool = True) -> str:
    return subprocess.run(["tmux", *args], check=check, capture_output=True, text=True).stdout


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "img" / "terminal.txt"))
    ap.add_argument("--timeout-s", type=float, default=600.0,
                    help="give up after this long [s] (default 600)")
    ap.add_argument("emulate_args", nargs="*", help="arguments of diffpos emulate "
                    f"(default: {' '.join(DEFAULT_ARGS)})")
    args = ap.parse_args()
    cmd = [str(DIFFPOS), "emulate", *(args.emulate_args or DEFAULT_ARGS)]
    session = f"diffpos-capture-{os.getpid()}"
    env = " ".join(f"{k}={shlex.quote(v)}" for k, v in os.environ.items()
                   if k in ("PYTHONPATH", "PATH", "HOME", "LANG"))
    shell = f"cd {shlex.quote(str(ROOT))} && env {env} {shlex.join(cmd)}"
    tmux("new-session", "-d", "-s", session, "-x", "80", "-y", "24", shell)
    try:
        tmux("set-option", "-t", session, "remain-on-exit", "on")
        tmux("set-option", "-t", session, "history-limit", "5000")
        deadline = time.monotonic() + args.timeout_s
        while tmux("list-panes", "-t", session, "-F", "#{pane_dead}").strip() != "1":
            if time.monotonic() > deadline:
                raise SystemExit(f"emulate did not finish in {args.timeout_s:g} s")
            time.sleep(0.5)  # poll the pane state (tmux has no blocking wait for it)
        text = tmux("capture-pane", "-p", "-t", session, "-S", "-5000")
    finally:
        tmux("kill-session", "-t", session, check=False)
    lines = text.rstrip("\n").splitlines()
    while lines and lines[-1].startswith("Pane is dead"):
        lines.pop()
    header = (f"$ diffpos {' '.join(cmd[1:])}    # tmux 80x24, captured by "
              "scripts/tmux_capture.py\n")
    Path(args.out).write_text(header + "\n".join(lines).rstrip() + "\n", encoding="utf-8")
    print(f"wrote {args.out} ({len(lines)} lines, widest {max(map(len, lines), default=0)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
