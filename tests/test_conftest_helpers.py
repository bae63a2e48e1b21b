"""The shared test helpers in tests/conftest.py find a test's own processes only."""

from __future__ import annotations

import os
import subprocess
import sys

from conftest import TEST_RUN_ENV

WAIT_STDIN = "import sys; print('up', flush=True); sys.stdin.read()  # own-processes probe"


def test_own_processes_sees_this_tests_processes_not_others(services):
    """A process carrying this test's tag is found by its command line; an identical one
    without the tag (a concurrent test's, another user's) is not; an exited one is gone."""
    tagged = dict(os.environ, **{TEST_RUN_ENV: str(services.log_dir)})
    mine = subprocess.Popen([sys.executable, "-c", WAIT_STDIN], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, env=tagged)
    other = subprocess.Popen([sys.executable, "-c", WAIT_STDIN], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE)
    try:
        # running, not just exec'd: Popen returns once exec closed its pipe, before the kernel
        # has set the new image's environment and command line (/proc reads them empty then:
        # one CI failure under load)
        assert mine.stdout.readline() == other.stdout.readline() == b"up\n"
        assert services.own_processes(b"own-processes probe") == [mine.pid]
        assert services.own_processes(b"no such command line") == []
    finally:
        for p in (mine, other):
            p.stdin.close()
            p.wait(timeout=30)
            p.stdout.close()
    assert services.own_processes(b"own-processes probe") == []
