"""What native (C/C++) libraries print on the process's stderr, kept from the user's
terminal: urdfdom, inside pinocchio's URDF parser, writes log lines with its build paths
(``Error: Failed to build tree ... at line 262 in /project/urdfdom/...``) straight to file
descriptor 2, before fwdstep's own one-line message.  ``captured_stderr`` catches them and
offers their reason for fwdstep's message instead."""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile


class NativeLog:
    """What was written to fd 2 inside ``captured_stderr`` (filled when the block ends,
    before an exception raised inside it reaches its handler)."""

    def __init__(self):
        self.text = ""

    @property
    def reason(self) -> str:
        """The first error line, without its level and without 'at line N in FILE' lines."""
        for line in self.text.splitlines():
            line = line.strip()
            if line.lower().startswith("error:"):
                return line.split(":", 1)[1].strip()
        return ""


@contextlib.contextmanager
def captured_stderr():
    """File descriptor 2 redirected to a temporary file while the block runs; yields a
    ``NativeLog`` holding what was written.  Python's own ``sys.stderr`` is flushed around
    it.  Process-wide (a file descriptor): keep the block to the one native call."""
    log = NativeLog()
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):    # no fd 2 (an embedded interpreter)
        yield log
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield log
        finally:
            try:
                sys.stderr.flush()
            except (OSError, ValueError):
                pass
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            log.text = tmp.read(1 << 16).decode("utf-8", errors="replace")
