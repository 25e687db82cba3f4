"""`python -m services.tb3_emulator` = `srl tb3-emulator`: the service's own command, no tools."""

from common.process.runtime import entry, service_parser
from services.tb3_emulator import command

entry(lambda: service_parser(command))
