"""`python -m services.robot_bridge` = `srl robot-bridge`: the service's own command, no tools."""

from common.process.runtime import entry, service_parser
from services.robot_bridge import command

entry(lambda: service_parser(command))
