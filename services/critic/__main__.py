"""`python -m services.critic` = `srl critic`: the service's own command, no tools."""

from common.process.runtime import entry, service_parser
from services.critic import command

entry(lambda: service_parser(command))
