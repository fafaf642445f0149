"""One Ctrl-C stops a job: exit status 130 and one line on stderr, at once.

Python raises ``KeyboardInterrupt`` in the main thread at its next bytecode, which can be inside
a garbage-collection callback of JAX, where the exception is printed as "Exception ignored" and
lost: the job then runs on. So ``main`` replaces that: the signal only wakes a watcher thread
(``signal.set_wakeup_fd``), which waits for any write in flight (``WRITING``: a cached cell and
its checksum, a results file, a page), stops the job's child processes (``spawn``), prints the
line and ends the process with status 130. The cache's cells are written atomically, so a rerun
resumes from the finished ones.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading

WRITING = threading.Lock()
"""Held while a job writes a file that must not be cut short; an interrupt waits for it."""

CHILDREN: set = set()
"""The job's live child processes (``spawn``), stopped on an interrupt."""

CACHED = "cached cells are kept, rerun to resume"

STOPPING = threading.Event()
"""Set by an interrupt before it stops the children: the main thread, woken by a killed child,
must not run on to a normal exit (status 0) before the interrupt ends the process (130)."""


def _stop(prog: str, note: str | None) -> None:
    """After the write in flight: stop the children, flush stdout, print the line, exit 130."""
    with WRITING:
        STOPPING.set()
        for child in list(CHILDREN):
            with contextlib.suppress(OSError):
                child.kill()
        with contextlib.suppress(Exception):
            sys.stdout.flush()
        print(f"{prog}: interrupted" + (f"; {note}" if note else ""), file=sys.stderr,
              flush=True)
        os._exit(130)


def _watch(fd: int, prog: str, note: str | None) -> None:
    """Read the signals the wakeup fd reports; stop at SIGINT; return when the fd closes."""
    try:
        while data := os.read(fd, 64):
            if signal.SIGINT in data:
                _stop(prog, note)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def stopping(prog: str, note: str | None = None):
    """Within: a SIGINT ends the process (status 130) with ``prog: interrupted[; note]``.
    Only in the main thread (where signals are handled); elsewhere it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    read, write = os.pipe()
    os.set_blocking(write, False)
    old_fd = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
    old_handler = signal.signal(signal.SIGINT, lambda *_: None)
    threading.Thread(target=_watch, args=(read, prog, note), daemon=True).start()
    try:
        yield
    finally:
        if STOPPING.is_set():  # the interrupt ends the process: wait for it
            threading.Event().wait()
        signal.signal(signal.SIGINT, old_handler)
        signal.set_wakeup_fd(old_fd)
        os.close(write)


def main(fn, prog: str, note: str | None = None, argv=None):
    """``fn(argv)`` (a job's ``main``) under ``stopping``: its ``__main__`` entry point."""
    with stopping(f"python -m experiments.{prog}", note):
        return fn(argv)


def spawn(args, **kwargs) -> subprocess.Popen:
    """``subprocess.Popen(args, **kwargs)`` in a process group of its own (a terminal's Ctrl-C
    reaches the job, not it), stopped with the job on an interrupt."""
    child = subprocess.Popen(args, start_new_session=True, **kwargs)
    CHILDREN.add(child)
    return child


def run(args, **kwargs) -> subprocess.CompletedProcess:
    """``subprocess.run(args, **kwargs)`` through ``spawn`` (``input``, ``check`` and
    ``timeout`` are not supported)."""
    if kwargs.pop("capture_output", False):
        kwargs |= {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE}
    child = spawn(args, **kwargs)
    try:
        out, err = child.communicate()
    finally:
        CHILDREN.discard(child)
        if child.poll() is None:
            child.kill()
            child.wait()
    # an interrupt kills the child while holding WRITING and then ends this process (status
    # 130): wait for it here, or the caller would go on with a killed child's status first
    with WRITING:
        return subprocess.CompletedProcess(child.args, child.returncode, out, err)
