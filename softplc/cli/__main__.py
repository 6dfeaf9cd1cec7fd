"""`python -m softplc.cli COMMAND`: the same as `softplc COMMAND`."""

import sys

from softplc.cli import main

sys.exit(main())
