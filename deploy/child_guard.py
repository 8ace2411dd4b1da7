"""Run a service module as a launcher child that cannot outlive the launcher.

    python -m deploy.child_guard PARENT_PID MODULE [ARGS...]

On Linux this asks the kernel (prctl PR_SET_PDEATHSIG) to send SIGTERM to this process when its
parent dies, then runs MODULE as `__main__` in this same process (no extra exec). Without it the
workers of a launcher killed with SIGKILL would keep retrying their router connection forever and
rejoin the next launcher's router as ghost workers. SIGTERM is what a worker turns into a clean
close, so an orphaned worker still undeclares and closes its session.

The kernel ties the signal to the parent *thread* that spawned the child, so the launcher spawns
every child from one long-lived thread.
"""
from __future__ import annotations

import ctypes
import os
import runpy
import signal
import sys

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> None:
    """Arrange SIGTERM on parent death (Linux); exit at once if the parent is already gone."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"prctl(PR_SET_PDEATHSIG) failed: {os.strerror(err)}")
    if os.getppid() != parent_pid:  # the launcher died before the guard was in place
        sys.exit(f"child_guard: launcher (pid {parent_pid}) is gone; not starting")


def main(argv: list[str]) -> None:
    if len(argv) < 2 or not argv[0].isdigit():
        sys.exit("usage: python -m deploy.child_guard PARENT_PID MODULE [ARGS...]")
    parent_pid, module, *args = argv
    die_with_parent(int(parent_pid))
    sys.argv = [module, *args]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main(sys.argv[1:])
