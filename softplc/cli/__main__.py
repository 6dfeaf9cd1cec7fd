"""`python -m softplc.cli COMMAND`: the same as `softplc COMMAND`."""

import sys

from softplc.cli import main

if __name__ == "__main__":  # imported (tests walk every module): nothing runs
    sys.exit(main())
