"""``python cli.py ...`` from a checkout: the ``fwdstep`` command.

The argument parser is installed as ``fwdstep.cli`` (so the distribution adds no top-level
module named ``cli``); this file only forwards to it.
"""
import sys

from fwdstep.cli.arguments import main

if __name__ == "__main__":
    sys.exit(main())
