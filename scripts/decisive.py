"""The decisive experiment's command line, moved to ``python -m gdbench.experiments.decisive``
(2026-11-27); this runs it for the command lines recorded before."""

import sys

from gdbench.experiments.decisive import main

if __name__ == "__main__":
    sys.exit(main())
