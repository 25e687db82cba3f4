"""`python -m services.plant_sim` = `srl plant-sim`."""

import sys

from services.cli import entry

entry(["plant-sim", *sys.argv[1:]])
