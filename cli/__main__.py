"""`python -m rover.cli`: the same as the `rover` command."""

import sys

from rover.cli.app import main

sys.exit(main())
