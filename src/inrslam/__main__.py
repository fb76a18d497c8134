"""`python -m inrslam ...` = the `inrslam` command."""

import sys

from inrslam.cli import main

sys.exit(main())
