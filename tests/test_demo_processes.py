"""The demo's daemons never outlive it, even when it is killed (SIGKILL, a test's timeout)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from tests.harness import ROOT

PARENT = r'''
import sys, time
from pathlib import Path
from sumoco.orchestrate.demo import Processes
procs = Processes(Path(sys.argv[1]))
child = procs.start("sleeper", [sys.executable, "-c", "import time; time.sleep(120)"])
print(child.pid, flush=True)
time.sleep(120)
'''


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"  # a zombie has ended
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_daemon_ends_when_the_demo_is_killed(tmp_path):
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                              cwd=ROOT)
    child = int(parent.stdout.readline())
    assert not _gone(child)
    parent.kill()
    parent.wait(10)
    deadline = time.monotonic() + 10.0
    while not _gone(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    if not _gone(child):
        os.kill(child, 9)
        pytest.fail("the daemon outlived the killed demo")
