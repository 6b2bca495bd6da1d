"""`python -m sagonline ...`: the command line (sagonline/apps/cli)."""

import sys

from sagonline.apps.cli import main

if __name__ == "__main__":
    sys.exit(main())
