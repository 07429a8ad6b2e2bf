"""``drillnav pki init|issue``: a site's certificate authority and one certificate per bus client."""

from __future__ import annotations

import argparse
from pathlib import Path

from .pki import CA_CERT, CA_KEY, init_ca, issue

__all__ = ["register"]


def _init(args: argparse.Namespace) -> int:
    ca = init_ca(Path(args.out), organisation=args.organisation, days=args.days)
    print(f"made a certificate authority: {ca} (give it to every client) and {ca.parent / CA_KEY} (mode 0600: keep it off the bus machines once the certificates are issued)")
    return 0


def _issue(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else Path(args.ca)
    made = []
    for name in args.name:
        made.append(issue(Path(args.ca), name, out, hosts=tuple(args.host or ()), days=args.days))
    for c in made:
        print(f"issued '{c.name}': {c.certificate} and {c.private_key} (mode 0600), valid until {c.not_after:%Y-%m-%d}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("pki", help="make the site's certificate authority and certificates for the zenoh bus")
    sub = p.add_subparsers(dest="pki_command", metavar="ACTION", required=True)

    i = sub.add_parser("init", help=f"make a certificate authority ({CA_CERT}, {CA_KEY}) in a folder")
    i.add_argument("--out", required=True, help="folder for the CA (created 0700)")
    i.add_argument("--organisation", default="drillnav site", help="the organisation named in the CA certificate")
    i.add_argument("--days", type=int, default=3650, help="validity of the CA")
    i.set_defaults(func=_init)

    s = sub.add_parser("issue", help="issue a certificate and key per client name, signed by the CA")
    s.add_argument("--ca", required=True, help="folder holding ca.pem and ca.key")
    s.add_argument("--name", required=True, action="append", help="the client's name, e.g. drillnav-daemon, camera-1, display-1 (repeatable): the certificate's common name, which access control matches")
    s.add_argument("--out", help="folder for <name>.pem and <name>.key (default: the CA folder)")
    s.add_argument("--host", action="append", help="a DNS name or IP address the holder is reached at, e.g. the daemon's (repeatable; loopback is always included)")
    s.add_argument("--days", type=int, default=825, help="validity of the certificate (capped at the CA's)")
    s.set_defaults(func=_issue)

