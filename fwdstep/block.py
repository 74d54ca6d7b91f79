"""Stable plugin import (docs/writing-blocks.md): ``fwdstep.block`` is ``fwdstep.core.block``.

The module object itself is installed under this name, so the classes, functions and the
registry are the very same objects whichever name a plugin imports."""
import sys

from fwdstep.core import block as _module

sys.modules[__name__] = _module
