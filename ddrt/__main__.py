"""`python -m ddrt ...` is the `ddrt` command: what a Python user tries first, and what works
from a venv whose scripts are not on PATH."""

import sys

from ddrt.cli import main

sys.exit(main())
