"""SIGINT, SIGTERM and SIGHUP end a run the same way: partial results kept, status
"interrupted", exit code 128 + the signal number (130, 143, 129).

``handled()`` (used by ``cli.main``) turns the three signals into ``Interrupted``, a
``KeyboardInterrupt`` subclass, so every place that already keeps partial results on Ctrl-C
(the run loop, sweeps) does the same for ``timeout``, a batch scheduler or a closed terminal.
``deferred()`` holds them back while results are being written: a signal that arrives then
is remembered (``pending()``) and the write completes.  Once one signal has ended the
command, later ones are ignored: the partial results are being saved and the user has been
told once (pressing Ctrl-C again and again never adds a second message or a traceback).
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading

#: what each signal is called in messages
REASONS = {signal.SIGINT: "interrupted by the user", signal.SIGTERM: "terminated (SIGTERM)",
           signal.SIGHUP: "hung up (SIGHUP)"}
HANDLED = tuple(REASONS)

_state = {"deferring": 0, "pending": None, "acted": 0}


class Interrupted(KeyboardInterrupt):
    """A handled signal arrived; ``signum`` says which."""

    def __init__(self, signum: int = signal.SIGINT):
        self.signum = signum
        super().__init__(REASONS.get(signum, f"signal {signum}"))

    @property
    def reason(self) -> str:
        return REASONS.get(self.signum, f"signal {self.signum}")


def exit_code(exc: BaseException | None) -> int:
    """128 + the signal number of an interruption (130 for a plain KeyboardInterrupt)."""
    return 128 + int(getattr(exc, "signum", signal.SIGINT))


def reason(exc: BaseException | None) -> str:
    return getattr(exc, "reason", REASONS[signal.SIGINT])


def _handler(signum, frame):
    if _state["acted"]:                  # the command is already ending on an earlier one
        return
    if _state["deferring"]:
        _state["pending"] = _state["pending"] or signum
        return
    _state["acted"] = signum
    raise Interrupted(signum)


@contextlib.contextmanager
def handled():
    """Install the handlers for the duration of a command (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    for signum in HANDLED:
        try:
            previous[signum] = signal.signal(signum, _handler)
        except (OSError, ValueError):        # not available on this platform
            pass
    _state["pending"], _state["acted"] = None, 0
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


@contextlib.contextmanager
def deferred():
    """Hold handled signals back while results are written (the write always completes)."""
    _state["deferring"] += 1
    try:
        yield
    finally:
        _state["deferring"] -= 1


def pending() -> Interrupted | None:
    """The interruption that arrived during ``deferred()`` (then forgotten), or None."""
    signum, _state["pending"] = _state["pending"], None
    if signum:
        _state["acted"] = signum             # it ends the command: later ones are ignored
    return Interrupted(signum) if signum else None


@contextlib.contextmanager
def held():
    """Hold SIGINT, SIGTERM and SIGHUP back during a short step that must complete together
    with its bookkeeping (a compiled chunk: numba never looks at signals, so one arriving
    during the chunk is raised by Python the moment the chunk returns, before its rows were
    counted, and they were lost).  The signal is raised when the block ends.  Under
    ``handled()`` this is ``deferred()``; otherwise (the Python API, main thread) a
    temporary handler records SIGINT and the block ends as the handler it replaced would
    have acted (Python's own: ``KeyboardInterrupt``; an ignored SIGINT stays ignored)."""
    current = signal.getsignal(signal.SIGINT)
    ours = current is _handler
    if ours or current is None or threading.current_thread() is not threading.main_thread():
        if ours:
            with deferred():
                yield
            late = pending()
            if late is not None:
                raise late
        else:
            yield
        return
    caught = []
    try:
        previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    except (OSError, ValueError):
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught and callable(previous):          # Python's own raises KeyboardInterrupt
        previous(signal.SIGINT, None)
    elif caught and previous == signal.SIG_DFL:
        os.kill(os.getpid(), signal.SIGINT)    # what it would have done: end the process
