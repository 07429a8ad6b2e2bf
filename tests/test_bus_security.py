"""The secured bus against real zenoh on loopback: TLS, mutual TLS, user/password and access control.

The proof the issue asks for: a peer without credentials (or with a
certificate from another CA, or with the site's certificate but the wrong
role) can neither publish a drill axis that a display sees nor inject a shot
that the daemon takes, while the daemon publishes and a credentialed
read-only client (the README's client, run as written) receives. Certificates
come from drillnav's own pki code, in a temporary folder.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from conftest import free_port
from drillnav.service.bus import BusError, open_session
from drillnav.service.bus_policy import is_loopback
from drillnav.service.pki import init_ca, issue
from drillnav.service.settings import SettingsError, ZenohSettings, load_settings

pytestmark = pytest.mark.timeout(60)

PREFIX = "drillnav"  # the README client subscribes to drillnav/axis/carm; ports keep runs apart
AXIS = f"{PREFIX}/axis/carm"
SHOT = f"{PREFIX}/fluoro/shot"
CLIENT = Path(__file__).resolve().parents[1] / "docs" / "examples" / "axis_client.py"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pki")
    site = root / "site"
    init_ca(site)
    for name in ("drillnav-daemon", "camera-1", "carm-1", "display-1"):
        issue(site, name, site)
    rogue = root / "rogue"  # a CA the site never trusted, issuing the daemon's name
    init_ca(rogue)
    issue(rogue, "drillnav-daemon", rogue)
    return site


def _daemon_section(site: Path, endpoint: str, *also_listen: str, **access) -> ZenohSettings:
    return ZenohSettings(
        mode="peer", listen=[endpoint, *also_listen], prefix=PREFIX,
        tls={"ca": site / "ca.pem", "certificate": site / "drillnav-daemon.pem", "private_key": site / "drillnav-daemon.key", "mutual": True},
        access_control={"enabled": True, "cameras": ["camera-1"], "carms": ["carm-1"], **access},
    )


def _client(site: Path, endpoint: str, name: str | None, **fields):
    tls = {"ca": site / "ca.pem", "mutual": name is not None}
    if name is not None:
        tls.update(certificate=site / f"{name}.pem", private_key=site / f"{name}.key")
    return open_session(mode="client", connect=[endpoint], prefix=PREFIX, tls=tls, **fields)


class Inbox:
    """Samples a subscriber received, with a wait that polls against a deadline."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.items: list[tuple[str, bytes]] = []

    def __call__(self, sample) -> None:
        with self._lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def payloads(self, key: str | None = None) -> list[bytes]:
        with self._lock:
            return [p for k, p in self.items if key is None or k == key]

    def wait_for(self, payload: bytes, *, publish, timeout_s: float = 5.0) -> None:
        """Publish (again and again: declarations take a moment to reach the publisher) until ``payload`` arrives."""
        deadline = time.monotonic() + timeout_s
        while payload not in self.payloads():
            if time.monotonic() > deadline:
                raise AssertionError(f"{payload!r} never arrived; got {self.payloads()}")
            publish()
            time.sleep(0.05)


def _forge(session, key: str, payload: bytes, times: int = 5) -> None:
    for _ in range(times):
        session.put(key, payload)
        time.sleep(0.02)


def test_unauthorised_peers_cannot_publish_an_axis_or_inject_a_shot(site):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    local = f"tcp/127.0.0.1:{free_port()}"  # a plain loopback listener too, for tools on the daemon's machine
    display, daemon_inbox = Inbox(), Inbox()
    with open_session(_daemon_section(site, endpoint, local, readers=["display-1"])) as daemon:
        daemon.declare_subscriber(SHOT, daemon_inbox)
        daemon.declare_subscriber(f"{PREFIX}/camera/**", daemon_inbox)
        with _client(site, endpoint, "display-1") as reader:
            reader.declare_subscriber(f"{PREFIX}/**", display)
            display.wait_for(b"axis-before", publish=lambda: daemon.put(AXIS, b"axis-before"))

            # no credentials at all: the TLS handshake wants a client certificate
            with pytest.raises(BusError, match="could not open"):
                _client(site, endpoint, None)
            # plain TCP at the TLS port
            with pytest.raises(BusError, match="could not open"):
                open_session(mode="client", connect=[endpoint.replace("tls/", "tcp/")])
            # the daemon's name on a certificate from a CA the site does not trust
            rogue = site.parent / "rogue"
            with pytest.raises(BusError, match="could not open"):
                open_session(mode="client", connect=[endpoint], tls={"ca": site / "ca.pem", "certificate": rogue / "drillnav-daemon.pem", "private_key": rogue / "drillnav-daemon.key"})

            # no credentials, through the plain listener: the session opens, access control drops what it sends
            anonymous_inbox = Inbox()
            with open_session(mode="peer", connect=[local]) as anonymous:
                anonymous.declare_subscriber(f"{PREFIX}/**", anonymous_inbox)
                _forge(anonymous, AXIS, b"forged-anonymously")
                _forge(anonymous, SHOT, b"shot-anonymously")
                time.sleep(0.2)
                daemon.put(AXIS, b"axis-not-for-strangers")
                time.sleep(0.2)

            # the site's certificates, the wrong roles: a display and a camera forging axes and shots
            with _client(site, endpoint, "display-1") as forger:
                _forge(forger, AXIS, b"forged-by-display")
                _forge(forger, SHOT, b"shot-by-display")
            with _client(site, endpoint, "camera-1") as camera:
                _forge(camera, AXIS, b"forged-by-camera")
                _forge(camera, SHOT, b"shot-by-camera")
                # ... while what a camera may publish still arrives (the rules select, they do not block everything)
                daemon_inbox.wait_for(b"frame", publish=lambda: camera.put(f"{PREFIX}/camera/image", b"frame"))
            with _client(site, endpoint, "carm-1") as carm:
                _forge(carm, AXIS, b"forged-by-carm")
                daemon_inbox.wait_for(b"shot-by-carm", publish=lambda: carm.put(SHOT, b"shot-by-carm"))
            # a daemon-role session elsewhere (a second process with the daemon's certificate) may publish outputs
            with _client(site, endpoint, "drillnav-daemon") as daemon2:
                display.wait_for(b"axis-by-daemon-role", publish=lambda: daemon2.put(AXIS, b"axis-by-daemon-role"))

            time.sleep(0.3)  # what was forged had its chance to travel; then a last real axis closes the window
            display.wait_for(b"axis-after", publish=lambda: daemon.put(AXIS, b"axis-after"))

    axes = set(display.payloads(AXIS))
    assert {b"axis-before", b"axis-by-daemon-role", b"axis-after"} <= axes
    assert not {p for p in axes if p.startswith(b"forged")}, axes
    shots = set(daemon_inbox.payloads(SHOT))
    assert shots == {b"shot-by-carm"}, shots
    # with readers named, a stranger does not even read (its own puts reach its own subscriber, inside its session)
    assert b"axis-not-for-strangers" in axes
    assert [p for p in anonymous_inbox.payloads() if not p.endswith(b"anonymously")] == []
    assert not any(p.startswith(b"shot-by") and p != b"shot-by-carm" for p in display.payloads())


def test_named_readers_only(site):
    """With readers named, a site certificate of another name may not even subscribe."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    outsider = Inbox()
    reader = Inbox()
    with open_session(_daemon_section(site, endpoint, readers=["display-1"])) as daemon:
        with _client(site, endpoint, "carm-1") as carm, _client(site, endpoint, "display-1") as display:
            carm.declare_subscriber(AXIS, outsider)
            display.declare_subscriber(AXIS, reader)
            reader.wait_for(b"axis", publish=lambda: daemon.put(AXIS, b"axis"))
            time.sleep(0.2)
            daemon.put(AXIS, b"axis-2")
            reader.wait_for(b"axis-2", publish=lambda: None)
    assert outsider.payloads() == []


def test_user_password_authentication_and_roles_by_username(site, tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("camera-1:cam-secret-1\ndisplay-1:disp-secret-1\n")
    users.chmod(0o600)
    endpoint = f"tls/127.0.0.1:{free_port()}"
    section = ZenohSettings(
        mode="peer", listen=[endpoint], prefix=PREFIX,
        tls={"ca": site / "ca.pem", "certificate": site / "drillnav-daemon.pem", "private_key": site / "drillnav-daemon.key", "mutual": False},
        auth={"dictionary_file": users},
        access_control={"enabled": True, "cameras": ["camera-1"]},
    )
    inbox = Inbox()
    with open_session(section) as daemon:
        daemon.declare_subscriber(f"{PREFIX}/**", inbox)
        with pytest.raises(BusError, match="could not open"):
            _client(site, endpoint, None, auth={"user": "camera-1", "password": "wrong-password"})
        with pytest.raises(BusError, match="could not open"):
            _client(site, endpoint, None)  # TLS alone, no password
        with _client(site, endpoint, None, auth={"user": "display-1", "password": "disp-secret-1"}) as display:
            _forge(display, f"{PREFIX}/camera/image", b"frame-by-display")
        with _client(site, endpoint, None, auth={"user": "camera-1", "password": "cam-secret-1"}) as camera:
            inbox.wait_for(b"frame-by-camera", publish=lambda: camera.put(f"{PREFIX}/camera/image", b"frame-by-camera"))
    assert b"frame-by-display" not in inbox.payloads()


def test_the_readme_client_receives_over_mutual_tls(site):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    axis = {"registration_id": 3, "sequence": 0, "point_mm": [1.0, 2.0, 3.0], "direction": [0.0, 0.0, 1.0], "predicted_error": {"position_mm": 1.02, "angle_deg": 0.78}}
    with open_session(_daemon_section(site, endpoint)) as daemon:
        proc = subprocess.Popen([sys.executable, str(CLIENT), endpoint, str(site), "display-1"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            lines: list[str] = []
            reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
            reader.start()
            deadline = time.monotonic() + 15
            while not any(line.startswith("axis 3.") for line in lines):
                assert proc.poll() is None, proc.stderr.read()
                assert time.monotonic() < deadline, f"the client printed no axis: {lines}"
                daemon.put(AXIS, json.dumps(axis))
                axis["sequence"] += 1
                time.sleep(0.1)
            proc.stdin.write("\n")
            proc.stdin.flush()
            assert proc.wait(timeout=10) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    printed = [line for line in lines if line.startswith("axis 3.")][0]
    assert "[1.0, 2.0, 3.0] mm" in printed and "±1.0 mm, ±0.8 deg" in printed


# --- settings: what is refused before anything opens ---------------------------------------------------------------

UNBOUND = 7447  # endpoints that are only validated here, never opened: zenoh's usual port, as an operator writes it


def test_listening_beyond_loopback_unsecured_is_refused_unless_insecure(site):
    wide = f"tcp/0.0.0.0:{free_port()}"
    with pytest.raises(SettingsError, match=r"zenoh.listen 'tcp/0.0.0.0:\d+'.*without TLS.*without authentication.*without access control.*zenoh.insecure = true"):
        load_settings(zenoh={"listen": [wide]})
    with pytest.raises(SettingsError, match="insecure = true"):
        open_session(listen=[wide])  # the same refusal for a session built from fields
    with pytest.raises(SettingsError, match="multicast_scouting"):
        load_settings(zenoh={"listen": [f"tcp/127.0.0.1:{UNBOUND}"], "multicast_scouting": True})
    with pytest.raises(SettingsError, match=f"connect 'tcp/10.1.2.3:{UNBOUND}'.*without TLS"):
        load_settings(zenoh={"listen": [], "connect": [f"tcp/10.1.2.3:{UNBOUND}"]})
    # TLS alone is not enough for a listener: it must know who connects and limit what they may do
    tls_only = {"listen": [f"tls/0.0.0.0:{UNBOUND}"], "tls": {"ca": str(site / "ca.pem"), "certificate": str(site / "drillnav-daemon.pem"), "private_key": str(site / "drillnav-daemon.key"), "mutual": False}}
    with pytest.raises(SettingsError, match="without authentication.*without access control"):
        load_settings(zenoh=tls_only)
    assert load_settings(zenoh={"listen": [wide], "insecure": True}).zenoh.insecure
    secured = {**tls_only, "tls": {**tls_only["tls"], "mutual": True}, "access_control": {"enabled": True}}
    assert load_settings(zenoh=secured).zenoh.access_control.enabled
    # loopback needs nothing
    assert load_settings(zenoh={"listen": [f"tcp/127.0.0.1:{UNBOUND}", f"tcp/[::1]:{UNBOUND + 1}", f"tcp/localhost:{UNBOUND + 2}"]})


def test_settings_name_missing_files_and_loose_keys(site, tmp_path, monkeypatch):
    with pytest.raises(SettingsError, match=r"zenoh.tls.ca: .*nowhere.pem does not exist"):
        load_settings(zenoh={"tls": {"ca": str(tmp_path / "nowhere.pem")}})
    loose = tmp_path / "loose.key"
    loose.write_bytes((site / "display-1.key").read_bytes())
    loose.chmod(0o644)
    with pytest.raises(SettingsError, match=r"zenoh.tls.private_key: .*loose.key is readable by other users \(mode 0644\): chmod 600"):
        load_settings(zenoh={"tls": {"certificate": str(site / "display-1.pem"), "private_key": str(loose)}})
    with pytest.raises(SettingsError, match="zenoh.tls.certificate and zenoh.tls.private_key go together"):
        load_settings(zenoh={"tls": {"certificate": str(site / "display-1.pem")}})
    with pytest.raises(SettingsError, match="zenoh.auth.user and zenoh.auth.password go together"):
        load_settings(zenoh={"auth": {"user": "display-1"}})
    with pytest.raises(SettingsError, match=r"zenoh.tls.certificate and zenoh.tls.private_key are needed to listen on tls/"):
        load_settings(zenoh={"listen": [f"tls/127.0.0.1:{UNBOUND}"], "tls": {"ca": str(site / "ca.pem")}})
    with pytest.raises(SettingsError, match="zenoh.access_control.enabled needs a way to know who a peer is"):
        load_settings(zenoh={"access_control": {"enabled": True}})
    with pytest.raises(SettingsError, match="is not a zenoh endpoint"):
        load_settings(zenoh={"listen": [f"127.0.0.1:{UNBOUND}"]})
    # environment variables reach the nested keys, and are checked the same way
    monkeypatch.setenv("DRILLNAV_ZENOH__TLS__CA", str(tmp_path / "env-ca.pem"))
    with pytest.raises(SettingsError, match="env-ca.pem does not exist"):
        load_settings()


def _listening_ports() -> set[int]:
    """TCP ports this process listens on (Linux /proc: its socket inodes in the kernel's LISTEN table)."""
    inodes = set()
    for fd in Path("/proc/self/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:  # 0A: LISTEN
                ports.add(int(f[1].rsplit(":", 1)[1], 16))
    return ports


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="reads Linux /proc")
def test_a_peer_without_endpoints_listens_nowhere():
    """zenoh's default for a peer is an unsecured listener on every interface (tcp/[::]:0); drillnav's sessions never take it."""
    before = _listening_ports()
    with open_session(connect=[]):
        assert _listening_ports() - before == set()
    port = free_port()
    with open_session(listen=[f"tcp/127.0.0.1:{port}"]):  # the check above can see a listener
        assert _listening_ports() - before == {port}


def test_the_generated_key_files_are_private(site):
    for key in site.glob("*.key"):
        assert os.stat(key).st_mode & 0o777 == 0o600, key


@pytest.mark.parametrize("interfaces, arrives", [(["lo"], True), (["nosuchif0"], False)])
def test_names_can_be_bound_to_a_network_interface(site, interfaces, arrives):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    inbox = Inbox()
    with open_session(_daemon_section(site, endpoint, interfaces=interfaces)) as daemon:
        daemon.declare_subscriber(f"{PREFIX}/camera/**", inbox)
        with _client(site, endpoint, "camera-1") as camera:
            if arrives:
                inbox.wait_for(b"frame", publish=lambda: camera.put(f"{PREFIX}/camera/image", b"frame"))
            else:
                _forge(camera, f"{PREFIX}/camera/image", b"frame", times=20)
                time.sleep(0.2)
    assert (b"frame" in inbox.payloads()) is arrives


# is_loopback reads the host only and never binds: any port the OS hands out will do. It is put in inside the test, so
# the test's id stays the same from one collection to the next.
@pytest.mark.parametrize("endpoint, loopback", [
    ("tcp/127.0.0.1:{port}", True), ("tls/127.0.0.2:{port}", True), ("tcp/[::1]:{port}", True), ("tcp/localhost:{port}", True),
    ("unixsock-stream//run/drillnav.sock", True), ("tcp/127.0.0.1:{port}?iface=lo", True),
    ("tcp/0.0.0.0:{port}", False), ("tcp/[::]:{port}", False), ("tls/navcart.local:{port}", False),
    ("tcp/192.168.1.20:{port}", False), ("serial//dev/ttyUSB0", False),
])
def test_what_counts_as_loopback(endpoint, loopback):
    endpoint = endpoint.format(port=free_port())
    assert is_loopback(endpoint) is loopback
