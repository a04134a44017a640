"""`python -m jaxloc`: the `jaxloc` command."""

import sys

from ._cli.main import console_main


sys.exit(console_main())
