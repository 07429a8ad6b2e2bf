"""The zenoh session: an embedded peer by default (no router needed), router/client for multi-host set-ups.

Security comes from zenoh itself, configured from drillnav's ``[zenoh]``
settings (docs/security.md): TLS on the links (the site CA, this node's
certificate and key, mutual TLS), zenoh's user/password authentication, and
access control (``bus_policy.access_control_config``). The settings are
checked before a session opens, so a bus that would reach the network
unsecured is refused with the reason, never opened.
"""

from __future__ import annotations

import json
from typing import Any

import zenoh
from pydantic import ValidationError

from drillnav.registration.errors import DrillnavError
from drillnav.schemas.topics import TOPICS, Delivery, key, topic_for_key

from .bus_policy import access_control_config, endpoint_protocol
from .settings import SettingsError, ZenohSettings, describe_validation_error

__all__ = ["BusError", "zenoh_config", "open_session", "bus_section", "qos", "qos_for_key", "declare_publisher", "put"]


class BusError(DrillnavError):
    """The zenoh session could not be opened (nothing to connect to, a TLS handshake refused, a port taken)."""


def bus_section(section: ZenohSettings | None = None, /, **fields: Any) -> ZenohSettings:
    """A checked ``[zenoh]`` section: ``section`` with ``fields`` replaced.

    Without a section the base is a bare peer that listens nowhere (not the
    daemon's default listener), as a tool or test connecting to a daemon wants.
    """
    base = section if section is not None else ZenohSettings(listen=[])
    if not fields:
        base.check()  # files can vanish between reading the settings and opening the bus
        return base
    try:
        return ZenohSettings.model_validate({**base.model_dump(), **fields})
    except ValidationError as exc:
        raise SettingsError(describe_validation_error(exc, prefix="zenoh")) from None


def _tls(section: ZenohSettings) -> dict | None:
    t = section.tls
    if t.ca is None and t.certificate is None:
        return None
    conf: dict[str, Any] = {
        "enable_mtls": t.mutual,
        "close_link_on_expiration": True,  # an expired certificate ends the link, not only the next handshake
    }
    if t.ca is not None:
        conf["root_ca_certificate"] = str(t.ca)
    if t.certificate is not None:
        # one identity per node: a zenoh peer both accepts and opens links
        for side in ("listen", "connect"):
            conf[f"{side}_certificate"] = str(t.certificate)
            conf[f"{side}_private_key"] = str(t.private_key)
    return conf


def zenoh_config(section: ZenohSettings) -> zenoh.Config:
    """The ``zenoh.Config`` for a checked ``[zenoh]`` section."""
    section.check()
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(section.mode))
    conf.insert_json5("scouting/multicast/enabled", "true" if section.multicast_scouting else "false")
    # Always explicit, even when empty: zenoh's default for a peer without endpoints is tcp/[::]:0, an unsecured
    # listener on every interface that gossip then advertises, which would bypass everything below.
    conf.insert_json5("listen/endpoints", json.dumps(list(section.listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(section.connect)))
    tls = _tls(section)
    if tls is not None:
        conf.insert_json5("transport/link/tls", json.dumps(tls))
        if not section.insecure:
            # a secured node opens and accepts only the link kinds it was configured with, so a locator learnt by
            # scouting (a stranger's plain tcp/ listener) is never dialled
            protocols = sorted({endpoint_protocol(e) for e in (*section.listen, *section.connect)})
            if protocols:
                conf.insert_json5("transport/link/protocols", json.dumps(protocols))
    auth = section.auth
    usrpwd: dict[str, str] = {}
    if auth.user is not None and auth.password is not None:
        usrpwd.update(user=auth.user, password=auth.password.get_secret_value())
    if auth.dictionary_file is not None:
        usrpwd["dictionary_file"] = str(auth.dictionary_file)
    if usrpwd:
        conf.insert_json5("transport/auth/usrpwd", json.dumps(usrpwd))
    if section.access_control.enabled:
        conf.insert_json5("access_control", json.dumps(access_control_config(section.prefix, section.access_control)))
    return conf


def open_session(section: ZenohSettings | None = None, /, **fields: Any) -> zenoh.Session:
    """Open a session (use as a context manager).

    ``open_session(settings.zenoh)`` for the daemon; ``open_session(connect=[ep])``
    (fields of the ``[zenoh]`` section) for tools and tests. Raises
    :class:`SettingsError` for a section that is refused, :class:`BusError`
    when zenoh cannot open it.
    """
    s = bus_section(section, **fields)
    try:
        return zenoh.open(zenoh_config(s))
    except zenoh.ZError as exc:
        where = ", ".join([*(f"listen {e}" for e in s.listen), *(f"connect {e}" for e in s.connect)]) or "no endpoints"
        raise BusError(f"the zenoh session could not open ({where}): {str(exc).split(' at ')[0]}") from None


# Each stream's delivery (schemas/topics.py) as zenoh's QoS. zenoh drops a put (congestion control DROP, its
# default) when its priority's queue on a link (two batches) stays full for a millisecond. At the default priority
# the node's overlay JPEGs filled that queue on a loaded machine and an axis published just after them was lost
# (tests/test_bus_delivery.py: 148 of 300 axes arrived at a client slow to read the overlays). Guidance now has a
# priority of its own, ahead of images, and is not express (an express sample takes a batch of its own and fills the
# queue again: 159 of 300): 300 of 300. It still drops rather than block: blocking would let one client that stops
# reading hold the node's frame loop for zenoh's wait_before_close (5 s), and the other clients lost a third of the
# axes meanwhile; dropping loses only that client's samples, which it sees as gaps in the axis's ``sequence``.
# Shots and calibrations block: one lost is a registration missed, and they are published off the frame path.
_QOS: dict[Delivery, dict[str, Any]] = {
    Delivery.GUIDANCE: {"congestion_control": zenoh.CongestionControl.DROP, "priority": zenoh.Priority.INTERACTIVE_HIGH},
    Delivery.EVERY: {"congestion_control": zenoh.CongestionControl.BLOCK, "priority": zenoh.Priority.DATA},
    Delivery.LATEST: {"congestion_control": zenoh.CongestionControl.DROP, "priority": zenoh.Priority.DATA},
}


def qos(name: str) -> dict[str, Any]:
    """zenoh's put/publisher QoS keywords for the topic ``name`` (a key of ``TOPICS``)."""
    return dict(_QOS[TOPICS[name].delivery])


def qos_for_key(prefix: str, key_expr: str) -> dict[str, Any]:
    """The QoS for a concrete key: its topic's, or every-sample at data priority for a key drillnav does not name."""
    topic = topic_for_key(prefix, key_expr)
    return dict(_QOS[topic.delivery if topic is not None else Delivery.EVERY])


def declare_publisher(session: zenoh.Session, prefix: str, name: str, view: str | None = None, **kwargs: Any) -> zenoh.Publisher:
    """A publisher on the topic ``name`` with its delivery's QoS."""
    return session.declare_publisher(key(prefix, name, view), **qos(name), **kwargs)


def put(session: zenoh.Session, prefix: str, name: str, data: bytes, view: str | None = None, **kwargs: Any) -> None:
    """One sample on the topic ``name`` with its delivery's QoS."""
    session.put(key(prefix, name, view), data, **qos(name), **kwargs)
