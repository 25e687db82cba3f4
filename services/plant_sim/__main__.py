"""`python -m services.plant_sim` = `srl plant-sim`: the service's own command, no tools."""

from common.process.runtime import entry, service_parser
from services.plant_sim import command

entry(lambda: service_parser(command))
