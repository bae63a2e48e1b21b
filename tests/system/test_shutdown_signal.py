"""A service's main thread waiting for its stop signal wakes even when the kernel delivers the
signal to another thread (a Zenoh thread): ``shutdown.Shutdown.wait`` blocks in slices, so Python
runs the handler. Before, a router child of a SIGKILLed ``diffpos emulate`` stayed blocked in
``Event.wait()`` under load (tests/system/test_emulate_faults.py, 1 run in 3-4 under load)."""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

#: readiness waits fail after this long [s] (a hang guard, not a speed target)
TIMEOUT_S = 30.0

_CHILD = textwrap.dedent("""
    import signal, sys, threading
    from diffpos_services.shutdown import Shutdown
    stop = Shutdown()
    ready = threading.Event()
    def blocked(tid):  # the main thread sleeps in the kernel (state S in /proc)
        with open(f"/proc/self/task/{tid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "S"
    def poke():  # SIGTERM to this thread, not the main one, once main waits
        ready.wait()
        tid = threading.main_thread().native_id
        while not blocked(tid):
            pass
        signal.pthread_kill(threading.get_ident(), signal.SIGTERM)
    threading.Thread(target=poke, daemon=True).start()
    ready.set()
    stop.wait() if sys.argv[1] == "shutdown" else stop.event.wait()  # "event": the old wait
    print("stopped", stop.signal_name, flush=True)
""")


def _run(how: str) -> subprocess.CompletedProcess | None:
    try:
        return subprocess.run([sys.executable, "-c", _CHILD, how], capture_output=True,
                              text=True, timeout=10)
    except subprocess.TimeoutExpired:
        return None


def test_shutdown_wait_wakes_on_a_signal_delivered_to_another_thread():
    done = _run("shutdown")  # _run("event") (the old plain Event.wait) times out
    assert done is not None and done.returncode == 0, done
    assert done.stdout.strip() == "stopped SIGTERM"


# A child (processes.child_env) whose parent dies gets SIGTERM once per thread of the dying parent
# that it is handed to on the way (kernel: the orphan is re-parented thread by thread, each
# time with its parent-death signal; 1-8 per child of a SIGKILLed 9-thread parent, measured;
# getppid() names the dying parent until the last). The repeats must not interrupt the
# child's orderly stop: a repeated SIGTERM is ignored, only a second SIGINT (Ctrl-C twice)
# raises KeyboardInterrupt. The test sends the repeats itself, so the case does not depend on
# how many the kernel sends.
_ORPHAN = textwrap.dedent("""
    import sys
    from diffpos_services.shutdown import Shutdown
    stop = Shutdown()
    print("ready", flush=True)
    stop.wait()
    print("stopping", stop.signal_name, flush=True)
    sys.stdin.readline()  # the orderly stop: until the test says "go"
    print("stopped cleanly", flush=True)
""")
_PARENT = textwrap.dedent("""
    import signal, subprocess, sys
    from diffpos_services.processes import child_env
    subprocess.Popen([sys.executable, "-c", sys.argv[1]], env=child_env())
    while True:
        signal.pause()  # idle until the test kills it
""")


def _lines(stream) -> queue.Queue:
    q: queue.Queue = queue.Queue()

    def read() -> None:
        for line in stream:
            q.put(line.strip())
        q.put(None)

    threading.Thread(target=read, daemon=True).start()
    return q


def _expect(q: queue.Queue, what: str) -> None:
    seen = []
    while True:
        line = q.get(timeout=TIMEOUT_S)
        assert line is not None, f"no {what!r}; output: {seen}"
        if line.startswith(what):
            return
        seen.append(line)


def _kill(p: subprocess.Popen, child: int | None) -> None:
    """SIGKILL the test's parent process and its child (if found); reap the parent."""
    for pid in (p.pid, child):
        if pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    p.wait(timeout=TIMEOUT_S)


def _orphan_pid(parent: int) -> int:
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError):
                stat = Path(f"/proc/{entry}/stat").read_text()
                if int(stat.rsplit(")", 1)[1].split()[1]) == parent:
                    return int(entry)
    raise AssertionError(f"no child of {parent}")


@pytest.mark.parametrize("case", ["parent dies, SIGTERM repeated", "SIGTERM repeated",
                                  "SIGINT twice"])
def test_repeated_sigterm_does_not_interrupt_the_stop_a_second_sigint_does(case):
    """Repeated SIGTERM (the parent dead, or dying: the kernel's repeats come while
    getppid() still names it): the child's stop runs to its end. SIGINT twice:
    KeyboardInterrupt (escape hatch)."""
    p = subprocess.Popen([sys.executable, "-c", _PARENT, _ORPHAN], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    child = None
    sig = signal.SIGINT if case == "SIGINT twice" else signal.SIGTERM
    try:
        out, err = _lines(p.stdout), _lines(p.stderr)
        _expect(out, "ready")
        child = _orphan_pid(p.pid)
        if case.startswith("parent dies"):
            os.kill(p.pid, signal.SIGKILL)  # the kernel sends the parent-death SIGTERM
            p.wait(timeout=TIMEOUT_S)
        else:
            os.kill(child, sig)
        _expect(out, f"stopping {sig.name}")
        # the repeats; SIGINT: a person's second Ctrl-C, one only (a third one can land while
        # the second's traceback is printed: Python then reports "lost sys.stderr" instead)
        for _ in range(3 if sig == signal.SIGTERM else 1):
            os.kill(child, sig)
        p.stdin.write("go\n")
        p.stdin.flush()
        if sig == signal.SIGTERM:
            _expect(out, "stopped cleanly")
        else:
            _expect(err, "KeyboardInterrupt")
    finally:
        _kill(p, child)


# The handler runs in the main thread between two bytecodes, possibly inside Event.wait while
# that thread holds the event's lock (every slice of Shutdown.wait takes it); setting the
# event must not wait for that lock. raise_signal runs the handler at once, here with the lock
# held as Event.wait holds it.
_LOCKED = textwrap.dedent("""
    import signal
    from diffpos_services.shutdown import Shutdown
    stop = Shutdown()
    with stop.event._cond:  # what Event.wait holds between its bytecodes
        signal.raise_signal(signal.SIGTERM)  # the handler runs in this thread, now
    print("set", stop.is_set(), flush=True)
""")


def test_handler_sets_the_event_while_the_main_thread_holds_its_lock():
    try:
        done = subprocess.run([sys.executable, "-c", _LOCKED], capture_output=True, text=True,
                              timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:  # a plain threading.Event deadlocks here
        pytest.fail("the signal handler waited for the lock its own thread held")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "set True"


# The program may set the event itself (a recorder whose --duration ran out: record() sets
# its stop event, then finishes the file). A person's first Ctrl-C then must not interrupt
# that finish (before: any signal with the event set raised KeyboardInterrupt, leaving the
# file without its footer); the second Ctrl-C still escapes. raise_signal runs the handler
# at once in the main thread.
_SELF_STOPPED = textwrap.dedent("""
    import signal
    from diffpos_services.shutdown import Shutdown
    stop = Shutdown()
    stop.set()  # the program's own stop (duration over)
    signal.raise_signal(signal.SIGINT)
    print("first Ctrl-C waits", stop.signal_name, flush=True)
    try:
        signal.raise_signal(signal.SIGINT)
    except KeyboardInterrupt:
        print("second Ctrl-C escapes", flush=True)
""")


def test_first_sigint_after_the_program_stopped_itself_does_not_interrupt_its_finish():
    try:
        done = subprocess.run([sys.executable, "-c", _SELF_STOPPED], capture_output=True,
                              text=True, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail("the child did not end")
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["first Ctrl-C waits None", "second Ctrl-C escapes"]


# Repeated SIGTERMs no longer interrupt a stop, so an orphan whose stop hangs has nobody left
# to end it: a supervised child (processes.child_env) exits by itself ``orphan_stop_s`` after its
# stop was asked once its parent is gone (shutdown.ORPHAN_STOP_S), and leaves a living parent to
# escalate itself. The child's stop here never ends (a wait on an event nobody sets).
_HUNG = textwrap.dedent("""
    import sys, threading
    from diffpos_services.shutdown import Shutdown
    stop = Shutdown(orphan_stop_s=0.3)
    print("ready", flush=True)
    stop.wait()
    print("stopping", stop.signal_name, flush=True)
    threading.Event().wait()  # a stop that hangs
""")


@pytest.mark.parametrize("parent", ["dies", "lives"])
def test_an_orphan_whose_stop_hangs_exits_by_itself_a_living_parent_decides(parent):
    p = subprocess.Popen([sys.executable, "-c", _PARENT, _HUNG], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    child = None
    try:
        out, err = _lines(p.stdout), _lines(p.stderr)
        _expect(out, "ready")
        child = _orphan_pid(p.pid)
        if parent == "dies":
            os.kill(p.pid, signal.SIGKILL)  # the kernel sends the parent-death SIGTERM
            p.wait(timeout=TIMEOUT_S)
        else:
            os.kill(child, signal.SIGTERM)
        _expect(out, "stopping SIGTERM")
        if parent == "dies":
            _expect(err, "diffpos: still stopping 0.3 s after the stop was asked and the "
                         "parent process is gone: exiting now")
            assert out.get(timeout=TIMEOUT_S) is None  # its end of the pipe closed: it exited
        else:
            _expect(err, "diffpos: still stopping; the parent process is alive: its call")
            assert Path(f"/proc/{child}").exists()  # still there: the parent's decision
            os.kill(p.pid, signal.SIGKILL)  # the parent goes: now the orphan exits
            p.wait(timeout=TIMEOUT_S)
            _expect(err, "diffpos: still stopping 0.3 s after")
    finally:
        _kill(p, child)
