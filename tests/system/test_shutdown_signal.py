"""A service's main thread waiting for its stop signal wakes even when the kernel delivers the
signal to another thread (a Zenoh thread): ``kit.Shutdown.wait`` blocks in slices, so Python
runs the handler. Before, a router child of a SIGKILLed ``diffpos emulate`` stayed blocked in
``Event.wait()`` under load (tests/system/test_emulate_faults.py, 1 run in 3-4 under load)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

_CHILD = textwrap.dedent("""
    import signal, sys, threading
    from diffpos_services.kit import Shutdown
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
