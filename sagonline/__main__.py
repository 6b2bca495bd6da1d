"""`python -m sagonline ...`: the command line (sagonline/cli)."""

import sys

from sagonline.cli import main

if __name__ == "__main__":
    sys.exit(main())
