"""The actor's JIT build: CasADi's generated C compiled by the machine's C compiler, safely.

* The build runs in a private temporary directory (:func:`jit_directory`), removed once the
  compiled code is loaded. Its name carries the building process's pid (``srl-jit-PID-*``):
  a directory whose process is gone (killed with SIGKILL mid-build) is removed by the next build
  and by ``srl up`` when its services have stopped (:func:`remove_orphan_build_directories`).
* A signal during the build stops the compiler and ends the build with
  :class:`BuildInterrupted` (exit 128 + the signal), never a half-built actor.
* Compiled objects are cached per user (:func:`default_jit_cache`), keyed by the SHA-256 of the
  compiler's version, the flags and the source; the least recently used are pruned. Two
  processes that need the same object compile it once: the second waits for the first's.

No srl concept lives here: the actor (common/math/actor_nlp.py) hands its functions to
:func:`build_with_jit` and gets them back compiled.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from typing import TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")


# The C compiler runs through this wrapper (CasADi's shell compiler calls system(), which
# ignores SIGINT in the caller and holds the GIL until gcc ends: minutes at a large N). gcc gets
# its own process group; the wrapper kills that group and removes the build directory when
# srl dies (SIGTERM/SIGKILL), when srl received SIGTERM/SIGINT (Python's C-level handler writes
# the signal number to SIGNALS, see jit_directory), or when the terminal's Ctrl-C reaches
# the wrapper itself; it leaves the signal number in SIGNALS for Python to report.
# With SRL_JIT_KEEPER set (a _SigintKeeper runs), gcc starts only once srl's SIGINT is no longer
# ignored (its /proc status, SigIgn): system() ignores it from its start until the keeper puts
# Python's handler back, and that takes as long as the keeper waits for a CPU; so for as long as
# the compiler runs, a SIGINT sent to srl alone is heard. The wait is bounded (~2 s): a build
# never hangs on the keeper.
# gcc runs niced (+10): on a machine where actors already tick (a fleet's second host, a test
# beside a run), their deadlines come first; alone, the niceness costs it nothing.
# With SRL_JIT_CACHE (a private directory, see jit_cache_directory), a compile (CasADi's
# ``cc FLAGS -c SOURCE -o OBJECT``) is looked up by the SHA-256 of the compiler's version, the
# flags and the source: the same problem compiles once per machine (CasADi's generated source
# is the same bits every build), and a compiled object is stored by an atomic rename. A source is
# compiled by one process at a time (flock on ``.KEY.lock`` beside the objects, where flock(1) is
# installed): a second process that needs it (a fleet's second actor host, an experiment's other
# worker, a test beside another) waits and takes the first one's object instead of compiling it too.
_JIT_WRAPPER = r"""#!/bin/sh
owner=$SRL_JIT_OWNER; dir=$(pwd); signals="$dir/SIGNALS"; cache=${SRL_JIT_CACHE:-}
TMPDIR="$dir"; export TMPDIR  # gcc's own temporaries (cc*.s) go with the build directory, even on SIGKILL
# srl gone (its build directory with it) or signalled: nothing to compile
going() { ! kill -0 "$owner" 2>/dev/null || [ -s "$signals" ] || [ ! -d "$dir" ]; }
going && exit 1
key=; src=; out=; previous=
for arg in "$@"; do
    case "$arg" in *.c) src=$arg;; esac
    [ "$previous" = "-o" ] && out=$arg
    previous=$arg
done
if [ -n "$cache" ] && [ -n "$src" ] && [ -n "$out" ]; then
    key=$({ "$1" --version 2>&1; for arg in "$@"; do
        case "$arg" in "$src") echo SOURCE;; "$out") echo OBJECT;; *) printf '%s\n' "$arg";; esac
    done; cat "$src"; } | sha256sum | cut -c1-64)
    cached() {
        [ -z "${SRL_JIT_CACHE_REFRESH:-}" ] && [ -f "$cache/$key.o" ] && cp "$cache/$key.o" "$out" &&
            touch "$cache/$key.o"
    }
    cached && exit 0
    if command -v flock >/dev/null 2>&1 && exec 9>"$cache/.$key.lock"; then  # one compile of a source at a time
        while ! flock -w 0.5 9; do  # another process compiles it: wait (srl gone or signalled: stop)
            going && exit 1
        done
        cached && exit 0  # ... and take its object
    fi
fi
if [ -n "${SRL_JIT_KEEPER:-}" ]; then  # srl hears SIGINT again before the compiler starts (_SigintKeeper)
    looks=0
    while [ "$looks" -lt 400 ] && kill -0 "$owner" 2>/dev/null && [ ! -s "$signals" ]; do
        ignored=$(sed -n "s/^SigIgn:[[:space:]]*//p" "/proc/$owner/status" 2>/dev/null)
        case "$ignored" in *[2367abef]) ;; *) break;; esac  # bit 1 of the mask: SIGINT ignored
        sleep 0.005; looks=$((looks + 1))
    done
fi
going && exit 1  # ... checked again: the waits above may have outlived srl (no compiler left running)
niced=; command -v nice >/dev/null 2>&1 && niced="nice -n 10"
setsid $niced "$@" &
child=$!
stop() { kill -KILL -"$child" 2>/dev/null; kill -KILL "$child" 2>/dev/null; }  # dash: no "--"
trap 'stop; printf "\002" >> "$signals"; exit 130' INT
trap 'stop; printf "\017" >> "$signals"; exit 143' TERM HUP
while state=$(sed -n "s/^.*) \(.\).*/\1/p" "/proc/$child/stat" 2>/dev/null) && [ -n "$state" ] && [ "$state" != Z ]
do
    if ! kill -0 "$owner" 2>/dev/null; then stop; rm -rf "$dir"; exit 1; fi
    if [ -s "$signals" ]; then stop; exit 1; fi
    sleep 0.1
done
wait "$child"
status=$?
if [ "$status" -eq 0 ] && [ -n "$key" ] && cp "$out" "$cache/.$key.$$"; then
    mv -f "$cache/.$key.$$" "$cache/$key.o" || rm -f "$cache/.$key.$$"
fi
exit "$status"
"""
JIT_CACHE_ENTRIES = 200  # compiled objects kept (~0.1-2 MB each); the least recently used go first


def srl_cache() -> str:
    """srl's per-user cache: ``$XDG_CACHE_HOME/srl`` (``~/.cache/srl``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "srl")


def default_jit_cache() -> str:
    """Where compiled actor problems are kept: ``$XDG_CACHE_HOME/srl/jit`` (``~/.cache/srl/jit``)."""
    return os.path.join(srl_cache(), "jit")


def jit_cache_directory(path: str) -> str | None:
    """``path`` made (mode 0700) if needed, or None, with a warning, if it cannot be made or
    another user could write to it: a compiled object from there is loaded into the process."""
    if not path:
        return None
    try:
        os.makedirs(path, mode=0o700, exist_ok=True)
        info = os.stat(path)
    except OSError as error:
        log.warning("JIT cache %s: %s: compiling without it", path, error.strerror or error)
        return None
    if info.st_uid != os.getuid() or info.st_mode & 0o022:
        log.warning("JIT cache %s is not private to this user (owner or mode): compiling without it", path)
        return None
    return path


def is_cached_object(name: str) -> bool:
    """A compiled object of the JIT cache (``KEY.o``; ``.KEY.PID`` is a store under way, ``.KEY.lock``
    its lock)."""
    return name.endswith(".o") and not name.startswith(".")


def cached_objects(path: str) -> set[str]:
    """The names of the compiled objects in the JIT cache ``path`` (none if it does not exist)."""
    try:
        return {name for name in os.listdir(path) if is_cached_object(name)}
    except FileNotFoundError:
        return set()


def prune_jit_cache(path: str, keep: int = JIT_CACHE_ENTRIES) -> None:
    """The ``keep`` most recently used objects stay; leftovers of a killed store (``.KEY.PID``,
    over an hour old) go."""
    try:
        entries = list(os.scandir(path))
        now = time.time()
        objects = sorted((e for e in entries if is_cached_object(e.name)), key=lambda e: e.stat().st_mtime)
        for entry in objects[: max(0, len(objects) - keep)]:
            os.remove(entry.path)
        for entry in entries:
            if entry.name.startswith(".") and now - entry.stat().st_mtime > 3600:
                os.remove(entry.path)
    except OSError as error:  # another build pruning too, or the directory gone: next time
        log.debug("JIT cache %s: pruning: %s", path, error)


BUILD_PREFIX = "srl-jit-"  # + the building process's pid + "-" + mkdtemp's random part


def remove_orphan_build_directories(parent: str | None = None, prefix: str = BUILD_PREFIX) -> int:
    """Remove the build directories (``srl-jit-PID-*`` in ``parent``, the temporary directory by
    default) of this user whose process is gone; returns how many. A directory of a running
    process (or of a pid reused since) is kept: only its own build removes it. ``prefix``: another
    kind of directory named ``PREFIX + PID + "-" + ...`` by the process that owns it (the test
    runner's)."""
    parent = parent or tempfile.gettempdir()
    removed = 0
    try:
        entries = list(os.scandir(parent))
    except OSError:
        return 0
    for entry in entries:
        pid = _build_owner(entry.name, prefix)
        if pid is None or _process_alive(pid):
            continue
        try:
            if not entry.is_dir(follow_symlinks=False) or entry.stat(follow_symlinks=False).st_uid != os.getuid():
                continue
        except OSError:
            continue
        removed += remove_build_directory(entry.path)
    return removed


def _build_owner(name: str, prefix: str = BUILD_PREFIX) -> int | None:
    """The pid in a build directory's name, None for any other name."""
    pid, dash, _ = name.removeprefix(prefix).partition("-")
    return int(pid) if name.startswith(prefix) and dash and pid.isdigit() else None


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process of that pid: alive
        return True
    return True


class BuildInterrupted(KeyboardInterrupt):
    """A signal ended the JIT build (its compiler killed, its directory removed)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"signal {signum} during the actor's JIT build")
        self.signum = signum


@contextlib.contextmanager
def jit_directory(cache: str = "", refresh: bool = False) -> Iterator[str]:
    """Run a JIT build inside a fresh private temporary directory, removed right after.

    CasADi writes its C files and shared objects into the CURRENT directory whatever its
    options say. Once built, the shared objects are loaded (dlopen), and removing their files
    leaves the mapping intact, so the directory is gone before the actor takes its first step:
    nothing is left in /tmp even when the process is later killed with SIGKILL.
    ``os.chdir`` is process-wide: actors are built before a service starts its threads, and
    the previous directory is restored even if the build fails. Directories left by builds whose
    process is gone (SIGKILL while CasADi wrote its C, before the wrapper ran) go first. Yields the compiler command
    (the wrapper above around gcc or cc). ``cache``: the directory of compiled objects kept
    across builds (see the wrapper; "" = none); ``refresh``: every object compiled and stored,
    none taken from it.
    """
    import signal
    import threading

    remove_orphan_build_directories()
    previous = os.getcwd()
    main = threading.current_thread() is threading.main_thread()
    owner = os.environ.get("SRL_JIT_OWNER")
    cache_before = os.environ.get("SRL_JIT_CACHE")
    cache_directory = jit_cache_directory(cache)
    # what the setup has done so far, undone in the finally whatever it had reached: a signal
    # (KeyboardInterrupt) may come at any line after the directory exists
    fd, old_fd, keeper = -1, -1, None
    path = tempfile.mkdtemp(prefix=f"{BUILD_PREFIX}{os.getpid()}-")
    try:
        wrapper = os.path.join(path, "cc.sh")
        with open(wrapper, "w") as file:
            file.write(_JIT_WRAPPER)
        os.chmod(wrapper, 0o700)
        signals = os.path.join(path, "SIGNALS")
        fd = os.open(signals, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NONBLOCK, 0o600)
        if main:
            old_fd = signal.set_wakeup_fd(fd, warn_on_full_buffer=False)
        os.environ["SRL_JIT_OWNER"] = str(os.getpid())
        os.environ.pop("SRL_JIT_CACHE", None)
        if cache_directory is not None:
            os.environ["SRL_JIT_CACHE"] = cache_directory
            if refresh:
                os.environ["SRL_JIT_CACHE_REFRESH"] = "1"
        os.chdir(path)
        compiler = f"{wrapper} {'gcc' if shutil.which('gcc') else 'cc'}"
        keeper = _SigintKeeper() if main else None
        os.environ.pop("SRL_JIT_KEEPER", None)  # this process's keeper only, never one inherited
        if keeper is not None and keeper.running:
            os.environ["SRL_JIT_KEEPER"] = "1"  # the wrapper waits for the keeper before gcc starts
        try:
            yield compiler
        except Exception as error:
            raise _build_signal(signals, error) from error
    finally:
        if keeper is not None:
            keeper.stop()
        if main and fd >= 0:
            signal.set_wakeup_fd(old_fd)
        if fd >= 0:
            os.close(fd)
        os.chdir(previous)
        if owner is None:
            os.environ.pop("SRL_JIT_OWNER", None)
        else:
            os.environ["SRL_JIT_OWNER"] = owner
        os.environ.pop("SRL_JIT_CACHE", None)
        os.environ.pop("SRL_JIT_CACHE_REFRESH", None)
        os.environ.pop("SRL_JIT_KEEPER", None)
        if cache_before is not None:
            os.environ["SRL_JIT_CACHE"] = cache_before
        remove_build_directory(path)
        if cache_directory is not None:
            prune_jit_cache(cache_directory)


REMOVE_TRIES = 40  # remove_build_directory: attempts, REMOVE_PAUSE_S apart (2 s in all)
REMOVE_PAUSE_S = 0.05


def remove_build_directory(path: str) -> bool:
    """Remove a build directory, again while something still writes into it: a compiler that a
    signal is stopping may create a file while the tree is being removed, which leaves the
    directory behind after one pass. Tries :data:`REMOVE_TRIES` times; True if it is gone."""
    for attempt in range(REMOVE_TRIES):
        shutil.rmtree(path, ignore_errors=True)
        if not os.path.lexists(path):
            return True
        if attempt + 1 < REMOVE_TRIES:
            time.sleep(REMOVE_PAUSE_S)
    log.warning("JIT build directory %s could not be removed", path)
    return False


KEEPER_POLL_SECONDS = 0.001  # _SigintKeeper: how soon SIGINT is heard again after system() ignores it


class _SigintKeeper:
    """Keep SIGINT heard while CasADi runs gcc through ``system()``.

    ``system()`` sets SIGINT to "ignore" in the whole process until gcc ends (POSIX), so a
    SIGINT sent to srl alone (``kill -INT``, not a terminal's Ctrl-C to the whole group) would
    be lost for the minutes of a large build. CasADi releases the GIL meanwhile, so this thread
    puts Python's own C-level handler back (read with ``sigaction`` before the build) within
    :data:`KEEPER_POLL_SECONDS`: the signal then reaches the wakeup file, and the wrapper stops
    gcc. A SIGINT inside that window, right as a ``system()`` starts, is lost (the kernel drops
    an ignored signal). The poll keeps the window short (1 ms, ~1,000 ``sigaction`` reads a
    second during a build, a few us each), but its real length is how long this thread waits for
    a CPU, unbounded on a loaded machine; so the wrapper starts gcc only once the handler is
    back (``SRL_JIT_KEEPER``, see _JIT_WRAPPER), and the window never overlaps the compiler's
    run, only the shell's start before it. ``system()`` restores the same handler when it
    returns. Linux/glibc only; elsewhere it does nothing (:attr:`running` false).
    """

    def __init__(self) -> None:
        import ctypes
        import signal
        import sys
        import threading

        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        if not sys.platform.startswith("linux"):
            return
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            saved = ctypes.create_string_buffer(256)  # >= sizeof(struct sigaction) (152 on x86_64)
            if libc.sigaction(signal.SIGINT, None, saved) != 0:
                return
        except (OSError, AttributeError):
            return
        handler = ctypes.c_void_p.from_buffer(saved).value  # sa_handler, the struct's first field
        if handler in (None, 0, 1):  # SIG_DFL or SIG_IGN: no Python handler to keep
            return

        def keep() -> None:
            current = ctypes.create_string_buffer(256)
            while not self._done.wait(KEEPER_POLL_SECONDS):
                if (
                    libc.sigaction(signal.SIGINT, None, current) == 0
                    and ctypes.c_void_p.from_buffer(current).value == 1
                ):  # SIG_IGN: system() runs gcc
                    libc.sigaction(signal.SIGINT, saved, None)

        self._thread = threading.Thread(target=keep, name="jit-sigint", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread is not None

    def stop(self) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)


def _build_signal(signals: str, error: Exception) -> BaseException:
    """The failed build's error, or :class:`BuildInterrupted` if a signal ended it."""
    try:
        with open(signals, "rb") as file:
            received = file.read()
    except OSError:
        received = b""
    return BuildInterrupted(received[0]) if received else error


def compiler_available() -> bool:
    return shutil.which("gcc") is not None or shutil.which("cc") is not None


def build_with_jit(functions: Callable[[str], T], cache: str) -> T:
    """``functions(compiler)`` inside a private JIT directory, the cache ``cache`` ("" = none).

    A build that fails with cached objects is done once more with every object compiled anew
    and replaced: a damaged cached object (a disk error, a file written by hand) must not stop
    the actor for good. A signal (:class:`BuildInterrupted`) is no Exception: it ends the build.
    """
    try:
        with jit_directory(cache) as compiler:
            return functions(compiler)
    except Exception as error:
        if not (cache and os.path.isdir(cache)):
            raise
        log.warning(
            "the JIT build with cached objects failed (%s): compiling it again and replacing them in %s",
            str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__,
            cache,
        )
        with jit_directory(cache, refresh=True) as compiler:
            return functions(compiler)
