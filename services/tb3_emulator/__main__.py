"""`python -m services.tb3_emulator` = `srl tb3-emulator`."""

import sys

from services.cli import main

sys.exit(main(["tb3-emulator", *sys.argv[1:]]))
