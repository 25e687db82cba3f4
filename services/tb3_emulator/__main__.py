"""`python -m services.tb3_emulator` = `srl tb3-emulator`."""

import sys

from services.cli import entry

entry(["tb3-emulator", *sys.argv[1:]])
