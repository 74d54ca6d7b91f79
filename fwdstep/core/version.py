"""fwdstep's version, declared once (``fwdstep.__version__``, ``fwdstep --version`` and the
record of every run, ``fwdstep.results.provenance``)."""
from __future__ import annotations

import os
import subprocess

__version__ = "0.1.0"


def source_commit() -> str | None:
    """The git commit of the fwdstep source tree this process imported, with '+changes' when
    its files differ from that commit; None outside a git checkout (an installed wheel)."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if not os.path.exists(os.path.join(os.path.dirname(here), ".git")):
        return None
    try:
        head = subprocess.run(["git", "-C", here, "rev-parse", "HEAD"], capture_output=True,
                              text=True, timeout=5, check=True).stdout.strip()
        changed = subprocess.run(["git", "-C", here, "status", "--porcelain",
                                  "--untracked-files=no", "--", "."], capture_output=True,
                                 text=True, timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+changes" if changed else "") if head else None
