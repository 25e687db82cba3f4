"""`python -m services.critic` = `srl critic`."""

import sys

from services.cli import main

sys.exit(main(["critic", *sys.argv[1:]]))
