"""`python -m services.plant_sim` = `srl plant-sim`."""

import sys

from services.cli import main

sys.exit(main(["plant-sim", *sys.argv[1:]]))
