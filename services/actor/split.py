"""``srl actor --robots ... --hosts H``: one command, H actor host processes.

A host's solves run in one thread, so a fleet that needs more than one core needs more than one
host process: ``srl up`` starts them itself (``--actor-hosts``); a container (compose's fleet
profile) or a hand-started host uses this. :func:`fork_shares` forks one child per share beyond
the first, BEFORE any session, thread or solver exists in the process: each child continues the
command as the host of its own share (its own Zenoh session, built problem and summary line), and
the parent serves the first share and supervises the others (:class:`Children`):

* a child that ends while the parent still serves stops the parent (a SIGTERM to itself, the
  services' clean stop), which then stops the other children: the command ends with a non-zero
  code and its supervisor (compose's restart policy, systemd) starts all of it again. The robots
  of the ended share meanwhile stop on their plants' watchdogs (zero velocity), as for any actor
  that vanished;
* when the parent stops (signal, ``--run-seconds``, an error), every child gets SIGTERM, then
  SIGKILL after :data:`STOP_GRACE_SECONDS`;
* when the parent is killed outright (SIGKILL), each child dies with it: ``SRL_PARENT_PID`` arms
  common/system/lifeline.py in the child (the kernel's parent-death signal and a watchdog).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time

from common.config.arguments import UsageError
from common.system.lifeline import PARENT_ENV

log = logging.getLogger(__name__)

STOP_GRACE_SECONDS = 10.0  # a child's clean stop (session closed, summary printed) takes ~1 s


class Children:
    """The parent's view of its child hosts: watched, and stopped with it."""

    def __init__(self, shares: dict[int, list[str]]) -> None:
        self.shares = shares  # pid -> the robots it serves
        self.codes: dict[int, int] = {}  # pid -> exit code (negative: the signal), once it ended
        self.stopping = threading.Event()
        for pid in shares:
            threading.Thread(target=self._watch, args=(pid,), name=f"actor-child-{pid}", daemon=True).start()

    def _watch(self, pid: int) -> None:
        try:
            _, status = os.waitpid(pid, 0)
        except ChildProcessError:
            return
        code = self.codes[pid] = os.waitstatus_to_exitcode(status)
        if not self.stopping.is_set():
            first, last = self.shares[pid][0], self.shares[pid][-1]
            how = f"was killed by {signal.Signals(-code).name}" if code < 0 else f"ended with exit code {code}"
            log.error("actor host process %d (robots %s .. %s) %s: stopping the others", pid, first, last, how)
            os.kill(os.getpid(), signal.SIGTERM)  # the parent's clean stop (common.process.runtime.serve)

    def stop(self) -> int:
        """SIGTERM to every child still running, SIGKILL after the grace; the worst exit code
        (0 if all ended cleanly; a child that had to be killed counts as -SIGKILL's 137)."""
        self.stopping.set()
        for signum in (signal.SIGTERM, signal.SIGKILL):
            for pid in self.shares:
                if pid not in self.codes:
                    if signum == signal.SIGKILL:
                        log.warning("actor host process %d did not stop in %.0f s: killed", pid, STOP_GRACE_SECONDS)
                    _signal(pid, signum)
            deadline = time.monotonic() + STOP_GRACE_SECONDS
            while time.monotonic() < deadline and len(self.codes) < len(self.shares):
                time.sleep(0.05)
        return max((128 - code if code < 0 else code for code in self.codes.values()), default=0)


def _signal(pid: int, signum: int) -> None:
    with contextlib.suppress(ProcessLookupError):  # it ended meanwhile
        os.kill(pid, signum)


def fork_shares(shares: list[list[str]]) -> tuple[list[str], Children | None]:
    """Fork one child per share after the first: ``(this process's share, its children)``. In a
    child: its own share and None. Refused if the process already runs a second thread (a fork
    copies only the calling thread: a lock held by another would stay held in the child)."""
    if len(shares) == 1:
        return shares[0], None
    if threading.active_count() != 1:
        raise UsageError("srl actor --hosts: cannot split after threads started (start it as its own command)")
    parent = os.getpid()
    sys.stdout.flush()  # nothing buffered is written twice
    sys.stderr.flush()
    children: dict[int, list[str]] = {}
    for share in shares[1:]:
        pid = os.fork()
        if pid == 0:  # the child: host of this share, dies with the parent
            os.environ[PARENT_ENV] = str(parent)
            return share, None
        children[pid] = share
    log.info(
        "actor hosts: %d processes (this one %d: %d robots; children %s)",
        len(shares),
        parent,
        len(shares[0]),
        ", ".join(f"{pid}: {len(share)}" for pid, share in children.items()),
    )
    return shares[0], Children(children)
