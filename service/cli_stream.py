"""``drillnav listen TOPIC``: print one JSON line per message of a drillnav stream."""

from __future__ import annotations

import argparse
import json
import threading
import time

# zenoh, the message codecs and the MCAP reader are imported by the commands: ``--help`` stays instant.

__all__ = ["register"]


def _listen(args: argparse.Namespace) -> int:
    from drillnav.schemas import messages as msg
    from drillnav.schemas.topics import ALIASES, TOPICS, Encoding, key

    from .bus import open_session

    name = ALIASES.get(args.topic, args.topic)
    if name not in TOPICS or "*" in TOPICS[name].suffix:
        raise ValueError(f"unknown topic '{args.topic}': one of {', '.join(sorted(ALIASES))}")
    if TOPICS[name].encoding is not Encoding.JSON:
        raise ValueError(f"topic '{args.topic}' carries images; listen prints JSON streams only")
    done = threading.Event()
    count = [0]

    def on_sample(sample) -> None:
        if done.is_set():
            return
        print(json.dumps(msg.decode_json(sample.payload.to_bytes())), flush=True)
        count[0] += 1
        if args.count and count[0] >= args.count:
            done.set()

    with open_session(mode="peer", connect=args.connect or [], multicast_scouting=False) as session:
        sub = session.declare_subscriber(key(args.prefix, name), on_sample)
        done.wait(args.timeout if args.timeout else None)
        sub.undeclare()
    return 0 if (not args.count or count[0] >= args.count) else 1


def register(subparsers) -> None:
    p = subparsers.add_parser("listen", help="print a stream as JSON lines (e.g. drill-axis)")
    p.add_argument("topic", help="drill-axis, status, events, markers, shots")
    p.add_argument("--connect", action="append", help="zenoh endpoint of the daemon, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--prefix", default="drillnav")
    p.add_argument("--count", type=int, default=0, help="stop after N messages")
    p.add_argument("--timeout", type=float, default=0.0, help="give up after S seconds")
    p.set_defaults(func=_listen)
    register_replay(subparsers)


def _replay(args: argparse.Namespace) -> int:
    from .bus import open_session
    from .replay import replay

    with open_session(mode="peer", listen=args.listen or [], connect=args.connect or [], multicast_scouting=False) as session:
        time.sleep(args.wait)  # let subscribers connect before the first message
        n = replay(args.file, session, rate=args.rate)
    print(f"replayed {n} messages from {args.file}")
    return 0


def register_replay(subparsers) -> None:
    p = subparsers.add_parser("replay", help="republish an MCAP recording at the recorded timing")
    p.add_argument("file")
    p.add_argument("--rate", type=float, default=1.0)
    p.add_argument("--listen", action="append", help="zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7448")
    p.add_argument("--connect", action="append", help="zenoh endpoint to connect to, e.g. the daemon's tcp/127.0.0.1:7447")
    p.add_argument("--wait", type=float, default=1.0, help="seconds to wait for subscribers before replaying")
    p.set_defaults(func=_replay)
