"""`python -m services.robot_bridge` = `srl robot-bridge`."""

import sys

from services.cli import main

sys.exit(main(["robot-bridge", *sys.argv[1:]]))
