"""``srl certs``: a private CA, the router's and each role's TLS certificate (mutual TLS,
docs/security.md), and with ``--passwords`` a random password per role."""

from __future__ import annotations

import argparse
from pathlib import Path

from common.config.arguments import UsageError

NAME = "certs"
HELP = "a private CA, the router's and each role's TLS certificate (mTLS)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out",
        required=True,
        help="directory to create (0700; files 0600); never in the repository (default: none, required)",
    )
    parser.add_argument(
        "--hosts",
        nargs="*",
        default=[],
        metavar="HOST",
        help="names/addresses clients use to reach the router, besides localhost, 127.0.0.1, ::1 (default: none)",
    )
    parser.add_argument(
        "--passwords",
        action="store_true",
        help="also a random password per role: users.txt (router) and <role>.password",
    )
    parser.add_argument(
        "--if-missing",
        action="store_true",
        help="exit 0 without writing if DIR already has a CA (default: write, and fail if it has one)",
    )
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """``srl certs --out DIR``: TLS material (common/net/certs.py) and, with --passwords, credentials."""
    from common.net.certs import write_tls_material
    from common.net.security import ROLES, write_credentials

    out = Path(args.out).expanduser()
    if (out / "ca.pem").exists():
        if args.if_missing:
            print(f"srl certs: {out} already holds a CA: kept", flush=True)
            return 0
        raise UsageError(f"{out} already holds a CA (ca.pem): choose a new directory (or --if-missing)")
    files = write_tls_material(out, ROLES, args.hosts)
    if args.passwords:
        write_credentials(out)
    print(
        f"srl certs: CA, router ({', '.join(['localhost', '127.0.0.1', '::1', *args.hosts])}) and "
        f"{', '.join(ROLES)} certificates{' and passwords' if args.passwords else ''} in {files.directory} "
        "(0700, files 0600)",
        flush=True,
    )
    return 0
