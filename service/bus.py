"""The zenoh session: an embedded peer by default (no router needed), router/client for multi-host set-ups."""

from __future__ import annotations

import json
from collections.abc import Sequence

import zenoh

__all__ = ["zenoh_config", "open_session"]


def zenoh_config(*, mode: str = "peer", listen: Sequence[str] = (), connect: Sequence[str] = (), multicast_scouting: bool = False) -> zenoh.Config:
    if mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode must be peer, client or router, got '{mode}'")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "true" if multicast_scouting else "false")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return conf


def open_session(**kwargs) -> zenoh.Session:
    """Open a session (use as a context manager); kwargs as :func:`zenoh_config`."""
    return zenoh.open(zenoh_config(**kwargs))
