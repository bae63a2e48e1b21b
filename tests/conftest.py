"""Shared test fixtures: the paper scenario, free ports and reaped service processes.

``services`` starts ``diffpos <service> ...`` processes in their own process group
(``start_new_session=True``) with their logs in the test's tmp dir, and in teardown sends
SIGTERM to every group, escalates to SIGKILL after a timeout and asserts nothing is left.
"""

from __future__ import annotations

import contextlib
import os
import resource
import signal
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest
from diffpos_services.processes import free_tcp_port, stop_process_groups

from diffpos.scenario import Scenario, default_scenario


@pytest.fixture(scope="module")
def paper() -> Scenario:
    """The paper's default scenario (one per test module)."""
    return default_scenario()


@pytest.fixture
def endpoint() -> str:
    """A fresh loopback Zenoh endpoint on a free port."""
    return f"tcp/127.0.0.1:{free_tcp_port()}"


#: environment variable every process a test starts (and their children) carries: the test's
#: log dir, so a test can find its own processes among those of concurrent tests (xdist) and
#: of other users of the machine
TEST_RUN_ENV = "DIFFPOS_TEST_RUN"


def thread_states(pid: int) -> str:
    """Each thread of ``pid``: its state, the system call it sleeps in (/proc ``syscall``:
    number and arguments, 202 = futex on x86_64; "running" if none) and its signal masks
    (pending, shared pending, blocked): what a process that did not stop on a signal was
    doing, for a failure message."""
    lines = []
    with contextlib.suppress(OSError):
        for tid in sorted(os.listdir(f"/proc/{pid}/task"), key=int):
            task = Path(f"/proc/{pid}/task/{tid}")
            with contextlib.suppress(OSError):
                status = dict(ln.split(":\t", 1) for ln in
                              (task / "status").read_text().splitlines() if ":\t" in ln)
                call = ""
                with contextlib.suppress(OSError):
                    call = (task / "syscall").read_text().split()[0]
                lines.append(f"  tid {tid}{' (main)' if tid == str(pid) else ''} "
                             f"{status.get('State', '?')} syscall {call or '?'} "
                             f"SigPnd {status.get('SigPnd', '?')} ShdPnd "
                             f"{status.get('ShdPnd', '?')} SigBlk {status.get('SigBlk', '?')}")
    return f"threads of {pid}:\n" + "\n".join(lines)


class ServiceProcesses:
    """Start and reap ``diffpos`` service processes for one test."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, *argv: str) -> subprocess.Popen:
        log = open(self.log_dir / f"{name}.log", "wb")
        env = dict(os.environ, DIFFPOS_LOG_FORMAT="text", **{TEST_RUN_ENV: str(self.log_dir)})
        env.pop("DIFFPOS_ZENOH_CONFIG", None)  # hermetic: the test says which bus
        p = subprocess.Popen(
            [sys.executable, "-m", "diffpos_services.cli.main", *argv],
            stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True, env=env,
        )
        log.close()
        self.procs[name] = p
        return p

    def log(self, name: str) -> str:
        path = self.log_dir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.procs[name].pid, sig)

    def own_processes(self, needle: bytes = b"") -> list[int]:
        """Pids of live processes this test started, directly or not (they inherit
        :data:`TEST_RUN_ENV`), whose command line holds ``needle``. Concurrent tests' and other
        users' processes are not counted (a scan of all of /proc fails under ``-n 2``)."""
        tag = f"{TEST_RUN_ENV}={self.log_dir}".encode()
        pids = []
        for proc in Path("/proc").iterdir():
            if not proc.name.isdigit():
                continue
            with contextlib.suppress(OSError):
                if (tag in (proc / "environ").read_bytes().split(b"\0")
                        and needle in (proc / "cmdline").read_bytes()):
                    pids.append(int(proc.name))
        return pids

    def check_running(self, ignore=()) -> None:
        """Raise (with its log) if a process other than those in ``ignore`` has exited."""
        for name, p in self.procs.items():
            if name not in ignore and p.poll() is not None:
                raise AssertionError(f"{name} exited early ({p.returncode}):\n{self.log(name)[-3000:]}")

    def stop(self, names: list[str] | None = None, timeout_s: float = 10.0) -> dict[str, int]:
        """SIGTERM the groups (in the given order), SIGKILL stragglers; return exit codes."""
        names = list(self.procs) if names is None else names
        return {name: stop_process_groups([self.procs[name]], timeout_s=timeout_s,
                                          on_kill=self._note_straggler(name))[0]
                for name in names}

    def _note_straggler(self, name: str):
        """``on_kill`` callback: append the straggler's :func:`thread_states` to its log (a
        failure message that shows the log's tail then says where it was stuck)."""
        def note(p: subprocess.Popen) -> None:
            with contextlib.suppress(OSError), open(self.log_dir / f"{name}.log", "a") as f:
                f.write(f"\n[test] no exit after SIGTERM, killing; {thread_states(p.pid)}\n")
        return note

    def reap_all(self) -> None:
        """Stop in reverse start order (the router, started first, goes last), each group
        SIGTERM then SIGKILL after 5 s; then check that no group member survived."""
        for p in reversed(list(self.procs.values())):
            stop_process_groups([p], timeout_s=5.0)
        for p in self.procs.values():
            assert p.returncode is not None
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, 0)
                os.killpg(p.pid, signal.SIGKILL)  # a grandchild survived: kill it


@pytest.fixture
def services(tmp_path):
    """Service processes reaped after the test (process groups, SIGTERM then SIGKILL)."""
    sp = ServiceProcesses(tmp_path)
    try:
        yield sp
    finally:
        sp.reap_all()


_SYSTEM_DIR = Path(__file__).resolve().parent / "system"


def pytest_collection_modifyitems(config, items) -> None:
    """Everything under tests/system/ (processes and a real bus) is marked ``system``, so the
    fast inner loop is ``pytest -m "not system"``."""
    for item in items:
        if _SYSTEM_DIR in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.system)


# --cpu-durations: on a shared machine wall-clock durations (--durations) mostly measure the
# other jobs; CPU seconds of the test process and of the children it waited for (the
# `diffpos ...` processes a test runs) are what a test costs. Works under xdist (the number
# travels in the report's user_properties).

def pytest_addoption(parser) -> None:
    parser.addoption("--cpu-durations", type=int, default=None, metavar="N",
                     help="show the N tests and test files using the most CPU time (test "
                          "process + waited-for children, setup to teardown); 0 for all")


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


_CPU_T0 = pytest.StashKey[float]()
_CPU_KEY = "cpu_s"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    item.stash[_CPU_T0] = _cpu_s()
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    if call.when == "teardown" and _CPU_T0 in item.stash:
        item.user_properties.append((_CPU_KEY, _cpu_s() - item.stash[_CPU_T0]))
    yield


_cpu_by_test: dict[str, float] = {}


def pytest_runtest_logreport(report) -> None:
    if report.when == "teardown":
        for key, value in report.user_properties:
            if key == _CPU_KEY:
                _cpu_by_test[report.nodeid] = value


def pytest_terminal_summary(terminalreporter, config) -> None:
    n = config.getoption("--cpu-durations")
    if n is None or not _cpu_by_test:
        return
    tr = terminalreporter
    ranked = sorted(_cpu_by_test.items(), key=lambda kv: -kv[1])
    by_file: dict[str, float] = defaultdict(float)
    for nodeid, cpu in ranked:
        by_file[nodeid.split("::")[0]] += cpu
    total = sum(by_file.values())
    tr.write_sep("=", f"CPU seconds per test file (process + children; total {total:.1f} s)")
    for path, cpu in sorted(by_file.items(), key=lambda kv: -kv[1])[:n or None]:
        tr.write_line(f"{cpu:8.2f}  {path}")
    tr.write_sep("=", "CPU seconds per test")
    for nodeid, cpu in ranked[:n or None]:
        tr.write_line(f"{cpu:8.2f}  {nodeid}")
