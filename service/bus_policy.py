"""What the zenoh bus may be: the settings checks, and the access-control rules drillnav gives zenoh.

Pure functions of the ``[zenoh]`` settings section (no zenoh import), so the
settings can refuse a configuration the moment they are read, and the rules
can be read and tested apart from a session. ``bus.py`` turns them into a
``zenoh.Config``; docs/security.md explains them to a site.

Why these checks: anyone who can publish on the bus can move the line the
surgeon drills along. A bus that only listens on loopback is reachable from
this machine alone; beyond it, drillnav wants TLS on every link, a way to know
who a peer is (mutual TLS or zenoh's user/password) and access control, or an
explicit ``insecure = true``.
"""

from __future__ import annotations

import ipaddress
import stat
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # settings imports this module; the types are for reading only
    from .settings import ZenohAccessSettings, ZenohSettings

__all__ = ["check_zenoh", "is_loopback", "endpoint_protocol", "exposures", "access_control_config", "output_keys", "camera_keys", "fluoro_keys", "TLS_PROTOCOLS"]

TLS_PROTOCOLS = frozenset({"tls", "quic"})  # zenoh's links that run TLS (both use transport/link/tls)
_LOCAL_PROTOCOLS = frozenset({"unixsock-stream", "unixpipe"})  # reachable through the file system only
_IP_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})


def endpoint_protocol(endpoint: str) -> str:
    """``'tls/0.0.0.0:7447'`` -> ``'tls'``; ValueError when it is not ``proto/address``."""
    proto, sep, address = endpoint.partition("/")
    if not sep or not proto or not address:
        raise ValueError(f"'{endpoint}' is not a zenoh endpoint (protocol/address, e.g. tls/192.168.10.5:7447)")
    return proto


def is_loopback(endpoint: str) -> bool:
    """True when only this machine can reach the endpoint (a loopback address or a local socket).

    A host name other than ``localhost``, ``0.0.0.0`` and ``[::]`` all reach
    beyond loopback; an unknown protocol is assumed to.
    """
    proto = endpoint_protocol(endpoint)
    if proto in _LOCAL_PROTOCOLS:
        return True
    if proto not in _IP_PROTOCOLS:
        return False
    address = endpoint.split("/", 1)[1].split("?", 1)[0].split("#", 1)[0]
    host = address.rsplit(":", 1)[0] if ":" in address else address
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def exposures(z: ZenohSettings) -> list[str]:
    """The ways the bus reaches beyond this machine, in words (empty: loopback only)."""
    out = [f"zenoh.listen '{e}'" for e in z.listen if not is_loopback(e)]
    out += [f"zenoh.connect '{e}'" for e in z.connect if not is_loopback(e)]
    if z.multicast_scouting:
        out.append("zenoh.multicast_scouting")
    return out


def _check_file(key: str, path: Path | None, *, secret: bool = False) -> None:
    if path is None:
        return
    p = Path(path)
    if not p.exists():
        raise ValueError(f"{key}: {p} does not exist")
    if not p.is_file():
        raise ValueError(f"{key}: {p} is not a file")
    mode = stat.S_IMODE(p.stat().st_mode)
    if secret and mode & 0o077:
        # the key or the passwords are the bus's identity: another account on the machine must not copy them
        raise ValueError(f"{key}: {p} is readable by other users (mode {mode:04o}): chmod 600 it")


def check_zenoh(z: ZenohSettings) -> None:
    """Raise ValueError, naming the setting, when the section cannot work or exposes the bus unsecured."""
    for where, endpoints in (("zenoh.listen", z.listen), ("zenoh.connect", z.connect)):
        for e in endpoints:
            try:
                endpoint_protocol(e)
            except ValueError as exc:
                raise ValueError(f"{where}: {exc}") from None
    tls, auth, acl = z.tls, z.auth, z.access_control
    _check_file("zenoh.tls.ca", tls.ca)
    _check_file("zenoh.tls.certificate", tls.certificate)
    _check_file("zenoh.tls.private_key", tls.private_key, secret=True)
    _check_file("zenoh.auth.dictionary_file", auth.dictionary_file, secret=True)
    if (tls.certificate is None) != (tls.private_key is None):
        raise ValueError("zenoh.tls.certificate and zenoh.tls.private_key go together: set both or neither")
    if (auth.user is None) != (auth.password is None):
        raise ValueError("zenoh.auth.user and zenoh.auth.password go together: set both or neither")

    listens_tls = any(endpoint_protocol(e) in TLS_PROTOCOLS for e in z.listen)
    connects_tls = any(endpoint_protocol(e) in TLS_PROTOCOLS for e in z.connect)
    if listens_tls and tls.certificate is None:
        raise ValueError("zenoh.tls.certificate and zenoh.tls.private_key are needed to listen on tls/ or quic/ endpoints")
    if (connects_tls or (listens_tls and tls.mutual)) and tls.ca is None:
        raise ValueError("zenoh.tls.ca (the site CA, 'drillnav pki init') is needed to verify the other end of a tls/ or quic/ link")
    if connects_tls and tls.mutual and tls.certificate is None:
        raise ValueError("zenoh.tls.mutual is on, so connecting over tls/ needs this node's zenoh.tls.certificate and zenoh.tls.private_key")

    mutual_tls = tls.mutual and tls.certificate is not None and (listens_tls or connects_tls)
    knows_names = mutual_tls or auth.dictionary_file is not None
    if acl.enabled and not knows_names:
        raise ValueError("zenoh.access_control.enabled needs a way to know who a peer is: mutual TLS (zenoh.tls with tls/ endpoints) or zenoh.auth.dictionary_file")

    exposed = exposures(z)
    if not exposed or z.insecure:
        return
    missing: list[str] = []
    plain = [e for e in (*z.listen, *z.connect) if not is_loopback(e) and endpoint_protocol(e) not in TLS_PROTOCOLS]
    if plain:
        missing.append(f"TLS (not a tls/ endpoint: {', '.join(plain)})")
    if any(not is_loopback(e) for e in z.listen) or z.multicast_scouting:
        # a listener beyond loopback is where strangers arrive: it must know them and limit them
        if not knows_names:
            missing.append("authentication (zenoh.tls.mutual with a certificate, or zenoh.auth.dictionary_file)")
        if not acl.enabled:
            missing.append("access control (zenoh.access_control.enabled)")
    if missing:
        raise ValueError(
            f"the bus reaches beyond this machine ({', '.join(exposed)}) without {'; without '.join(missing)}: "
            "any host on that network could publish a drill axis or inject a shot. "
            "Secure the bus (docs/security.md) or set zenoh.insecure = true to accept that risk"
        )


def output_keys(prefix: str) -> list[str]:
    """What the daemon alone publishes: the axis, overlays, registration status and events, marker poses."""
    return [f"{prefix}/axis/**", f"{prefix}/overlay/**", f"{prefix}/registration/**", f"{prefix}/fluoro/markers"]


def camera_keys(prefix: str) -> list[str]:
    return [f"{prefix}/camera/**"]


def fluoro_keys(prefix: str) -> list[str]:
    return [f"{prefix}/fluoro/shot", f"{prefix}/fluoro/*/image"]


def _subjects(role: str, names: list[str], interfaces: list[str]) -> list[dict]:
    """One subject per way a name is proven; zenoh ANDs the attributes of one subject, so they stay apart."""
    extra = {"interfaces": list(interfaces)} if interfaces else {}
    return [
        {"id": f"{role}-by-certificate", "cert_common_names": list(names), **extra},
        {"id": f"{role}-by-username", "usernames": list(names), **extra},
    ]


def access_control_config(prefix: str, access: ZenohAccessSettings) -> dict:
    """zenoh's ``access_control`` section for drillnav's roles (default deny).

    - the daemon's names may publish anything under the prefix (its outputs,
      and the inputs it makes itself: its camera's frames, the shots it receives);
    - camera names may publish ``<prefix>/camera/**``, C-arm names
      ``<prefix>/fluoro/shot`` and ``<prefix>/fluoro/*/image``;
    - readers (any peer that got through TLS or authentication when
      ``readers`` is unset) may subscribe and receive under the prefix;
    - nothing else passes: no publication from an unnamed peer, no queries,
      no deletions, nothing outside the prefix (the admin space included).

    Rules filter what arrives at this node (ingress) and what it sends on
    (egress), so a node in the middle (the daemon that clients connect to, or a
    router) protects everyone behind it.
    """
    everything = [f"{prefix}/**"]
    rules = [
        {"id": "subscribe", "permission": "allow", "messages": ["declare_subscriber"], "flows": ["ingress", "egress"], "key_exprs": everything},
        {"id": "receive", "permission": "allow", "messages": ["put"], "flows": ["egress"], "key_exprs": everything},
        {"id": "publish-all", "permission": "allow", "messages": ["put"], "flows": ["ingress"], "key_exprs": everything},
        {"id": "publish-camera", "permission": "allow", "messages": ["put"], "flows": ["ingress"], "key_exprs": camera_keys(prefix)},
        {"id": "publish-fluoro", "permission": "allow", "messages": ["put"], "flows": ["ingress"], "key_exprs": fluoro_keys(prefix)},
    ]
    # devices get "subscribe" so that the daemon's subscriptions reach them (an egress declaration), not to read
    roles = [
        ("daemon", access.daemon, ["subscribe", "receive", "publish-all"]),
        ("cameras", access.cameras, ["subscribe", "publish-camera"]),
        ("carms", access.carms, ["subscribe", "publish-fluoro"]),
    ]
    if access.readers is not None:
        roles.append(("readers", access.readers, ["subscribe", "receive"]))
    subjects: list[dict] = []
    policies: list[dict] = []
    for role, names, role_rules in roles:
        if not names:
            continue
        these = _subjects(role, names, access.interfaces)
        subjects += these
        policies.append({"id": role, "rules": role_rules, "subjects": [s["id"] for s in these]})
    if access.readers is None:
        anyone = {"id": "anyone", **({"interfaces": list(access.interfaces)} if access.interfaces else {})}
        subjects.append(anyone)
        policies.append({"id": "readers", "rules": ["subscribe", "receive"], "subjects": ["anyone"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
