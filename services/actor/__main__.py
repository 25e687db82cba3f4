"""`python -m services.actor` = `srl actor`."""

import sys

from services.cli import entry

entry(["actor", *sys.argv[1:]])
