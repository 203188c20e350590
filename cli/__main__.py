"""`python -m rover.cli`: the same as the `rover` command."""

import sys

from rover.cli.commands import main

sys.exit(main())
