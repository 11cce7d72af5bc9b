"""Blinded sheets for labelling results by eye, moved to ``python -m gdbench.metrics.label_sheets``
(2026-11-28); this runs it for the command lines recorded before."""

import sys

from gdbench.metrics.label_sheets import main

if __name__ == "__main__":
    sys.exit(main())
