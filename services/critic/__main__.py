"""`python -m services.critic` = `srl critic`."""

import sys

from services.cli import entry

entry(["critic", *sys.argv[1:]])
