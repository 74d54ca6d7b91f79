"""The ``fwdstep`` command line: ``main`` parses arguments (fwdstep.cli.arguments) and calls the verbs
(fwdstep.cli.commands and the ``cmd_*`` functions of the views and sweeps)."""
from fwdstep.cli.arguments import main

__all__ = ["main"]
