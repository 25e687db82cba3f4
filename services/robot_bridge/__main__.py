"""`python -m services.robot_bridge` = `srl robot-bridge`."""

import sys

from services.cli import entry

entry(["robot-bridge", *sys.argv[1:]])
