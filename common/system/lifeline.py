"""A service started by a supervisor (``srl up``) dies with it, however the supervisor dies.

The supervisor puts its pid into ``SRL_PARENT_PID``. :func:`die_with_parent` then arms two
independent guards in the service:

* Linux ``prctl(PR_SET_PDEATHSIG, SIGTERM)``: the kernel sends SIGTERM when the parent exits
  (even by SIGKILL); the service's SIGTERM handler stops it cleanly (the bridge's last zero
  still goes out). Linux only, through ctypes; elsewhere skipped.
* a watchdog thread that polls the parent pid every :data:`POLL_SECONDS` and sets ``stop`` when
  the parent is gone (``getppid()`` changed: re-parented to init or a subreaper) -- for kernels
  or sandboxes where the signal does not come. If the service has still not ended
  :data:`EXIT_GRACE_SECONDS` later, the watchdog ends the process (exit code 3).

Both need the interpreter: a stop that hangs in native code holding the GIL (a session close
waiting for a callback that waits for the GIL: a known kind of Zenoh binding deadlock) would
outlive them. So every stop also arms :func:`end_if_stuck` (the orphan's, and any service's stop
on a signal: ``common.process.runtime.serve``): faulthandler's C watchdog thread, which needs no GIL,
writes every thread's traceback to stderr and ends the process (exit code 1) if it still runs
:data:`HARD_EXIT_SECONDS` later.

Without ``SRL_PARENT_PID`` (a service started by hand, by a test, by a container runtime)
nothing is armed.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import faulthandler
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from typing import Any

log = logging.getLogger(__name__)

PARENT_ENV = "SRL_PARENT_PID"
PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
POLL_SECONDS = 0.2
EXIT_GRACE_SECONDS = 10.0  # longer than srl up's own stop grace (5 s): a clean stop normally wins
ORPHAN_EXIT_CODE = 3
HARD_EXIT_SECONDS = 12.0  # a stop's last resort, GIL-free (end_if_stuck); a clean stop takes ~1 s


def end_if_stuck(seconds: float | None = None) -> None:
    """The last resort of a stop: if this process still runs ``seconds`` (default
    :data:`HARD_EXIT_SECONDS`) from now, faulthandler's watchdog thread (C, no GIL needed) writes
    every thread's traceback to stderr -- what hung, for its report -- and ends it with exit code
    1. Armed once: a later call does not move it."""
    global _stuck_armed
    if _stuck_armed:
        return
    _stuck_armed = True
    faulthandler.dump_traceback_later(HARD_EXIT_SECONDS if seconds is None else seconds, exit=True)


_stuck_armed = False


def parent_pid() -> int | None:
    """The supervisor's pid from ``SRL_PARENT_PID``, or None (unset or not a positive integer)."""
    text = os.environ.get(PARENT_ENV, "")
    try:
        pid = int(text)
    except ValueError:
        if text:
            log.warning("%s=%r is not a pid: not watching the parent", PARENT_ENV, text)
        return None
    return pid if pid > 0 else None


def set_parent_death_signal(signum: int = signal.SIGTERM) -> bool:
    """``prctl(PR_SET_PDEATHSIG, signum)`` on Linux; False where it is not available."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(signum), 0, 0, 0) != 0:
            log.warning("prctl(PR_SET_PDEATHSIG) failed: %s", os.strerror(ctypes.get_errno()))
            return False
    except (OSError, AttributeError) as error:
        log.warning("prctl(PR_SET_PDEATHSIG) unavailable: %s", error)
        return False
    return True


def die_with_parent(stop: threading.Event) -> int | None:
    """Arm both guards if ``SRL_PARENT_PID`` is set; the parent pid watched (None: not armed).

    If the parent is already gone (it died before this call), ``stop`` is set at once."""
    parent = parent_pid()
    if parent is None:
        return None
    set_parent_death_signal(signal.SIGTERM)
    if os.getppid() != parent:  # died before the signal was armed: the kernel will not send it now
        log.warning("parent %d is gone: stopping", parent)
        stop.set()

    def watch() -> None:
        while not stop.wait(POLL_SECONDS):
            if os.getppid() != parent:
                log.warning("parent %d is gone: stopping", parent)
                stop.set()
                break
        if os.getppid() == parent:
            return  # an ordinary stop: the parent is alive and waits for us
        end_if_stuck()  # if the interpreter hangs too, the exit below never runs: this one does
        deadline = time.monotonic() + EXIT_GRACE_SECONDS
        while time.monotonic() < deadline:
            time.sleep(POLL_SECONDS)
        log.error("still running %.0f s after the parent died: exiting", EXIT_GRACE_SECONDS)
        os._exit(ORPHAN_EXIT_CODE)

    threading.Thread(target=watch, name="lifeline", daemon=True).start()
    return parent


def stop_group(process: subprocess.Popen[Any], grace: float) -> bool:
    """Stop a child started in a process group of its own (``process_group=0``) as a terminal's
    Ctrl-C would: SIGINT to the group, then SIGKILL to it if the child is still running after
    ``grace`` seconds, or at once if the wait is interrupted (a second Ctrl-C); waits for the
    child. True if it had to be killed. A child already gone (or ending meanwhile) is no error."""
    if process.poll() is not None:
        return False
    with contextlib.suppress(ProcessLookupError):  # it ended meanwhile
        os.killpg(process.pid, signal.SIGINT)
    try:
        process.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        pass
    finally:
        killed = process.poll() is None
        if killed:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    return killed
