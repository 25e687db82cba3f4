"""`python -m services.actor` = `srl actor`: the service's own command, no tools."""

from common.process.runtime import entry, service_parser
from services.actor import command

entry(lambda: service_parser(command))
