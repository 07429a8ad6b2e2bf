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
    from drillnav.schemas.calibration import read_camera_calibration, read_drill_calibration, read_drill_uncertainty
    from drillnav.schemas.markers import read_marker_set
    from .bus import open_session

    from .replay import RecordingReader, replay, replay_node

    RecordingReader(args.file)  # a missing file is refused before the bus opens
    with open_session(mode="peer", listen=args.listen or [], connect=args.connect or [], multicast_scouting=False) as session:
        node = None
        if args.register:
            # The calibrations given, else the ones the file carries (every recorded file starts with them).
            node = replay_node(args.file, session=session, prefix=args.prefix,
                               marker_set=read_marker_set(args.markers) if args.markers else None,
                               camera=read_camera_calibration(args.camera) if args.camera else None,
                               axis_drill=read_drill_calibration(args.drill) if args.drill else None,
                               axis_uncertainty=read_drill_uncertainty(args.drill) if args.drill else None)
        try:
            time.sleep(args.wait)  # let subscribers connect before the first message
            result = replay(args.file, session, rate=args.rate, state_settle_s=args.settle)
            if node is not None:
                time.sleep(1.0)  # the last frames' axes
        finally:
            if node is not None:
                node.close()
    print(f"replayed {result.messages} messages from {args.file}" + (f"; {result.cut}" if result.cut else ""))
    if node is not None:
        print(f"registration node: {node.counters.registrations} registration(s), {node.counters.axes_published} axes published")
    return 0


def register_replay(subparsers) -> None:
    p = subparsers.add_parser("replay", help="republish an MCAP recording at the recorded timing (also a file cut by a crash, up to the cut)")
    p.add_argument("file")
    p.add_argument("--rate", type=float, default=1.0)
    p.add_argument("--listen", action="append", help="zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7448")
    p.add_argument("--connect", action="append", help="zenoh endpoint to connect to, e.g. the daemon's tcp/127.0.0.1:7447")
    p.add_argument("--prefix", default="drillnav")
    p.add_argument("--wait", type=float, default=1.0, help="seconds to wait for subscribers before replaying")
    p.add_argument("--settle", type=float, default=2.0, help="seconds to pause after the state a file starts with (shots register before frames follow)")
    p.add_argument("--register", action="store_true", help="run a registration node here and publish the axes again")
    p.add_argument("--camera", help="camera.json for --register (default: the calibration recorded in the file)")
    p.add_argument("--drill", help="drill.json for --register (default: the calibration recorded in the file)")
    p.add_argument("--markers", help="markers file for --register (default: the file's, else the standard design)")
    p.set_defaults(func=_replay)
