"""The daemon's settings: one object, from a TOML file and DRILLNAV_* environment variables.

Precedence, highest first: the arguments ``load_settings`` is given (the CLI's
flags), then ``DRILLNAV_*`` environment variables (``DRILLNAV_API__PORT=8081``),
then the TOML file, then the defaults; sections merge key by key, so
``DRILLNAV_API__PORT`` keeps the file's ``[api] token``. Unknown keys and
invalid values are refused with the field named: a medical device must not
silently replace a bad setting with a default.
"""

from __future__ import annotations

import tomllib
from contextvars import ContextVar
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, InitSettingsSource, PydanticBaseSettingsSource, SettingsConfigDict

from drillnav.registration.errors import DrillnavError

from .bus_policy import check_zenoh

__all__ = ["Settings", "SettingsError", "load_settings", "describe_validation_error", "ZenohSettings"]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ZenohTlsSettings(_Section):
    ca: Path | None = Field(None, description="the site CA certificate (ca.pem from 'drillnav pki init'): verifies the peer's certificate")
    certificate: Path | None = Field(None, description="this node's certificate (PEM, from 'drillnav pki issue'); its common name is the name access control knows it by")
    private_key: Path | None = Field(None, description="this node's private key (PEM, mode 0600)")
    mutual: bool = Field(True, description="mutual TLS: a listener accepts only peers with a certificate from the CA")


class ZenohAuthSettings(_Section):
    user: str | None = Field(None, min_length=1, description="the name this node gives when it connects (zenoh usrpwd)")
    password: SecretStr | None = Field(None, description="its password (better from DRILLNAV_ZENOH__AUTH__PASSWORD than in a file)")
    dictionary_file: Path | None = Field(None, description="user:password lines a listener accepts (mode 0600)")


class ZenohAccessSettings(_Section):
    """Who may do what on the bus; each name matches a certificate's common name or a zenoh username."""

    enabled: bool = False
    daemon: list[str] = Field(default_factory=lambda: ["drillnav-daemon"], description="may publish everything, the outputs (axis, overlay, registration, fluoro/markers) included")
    cameras: list[str] = Field(default_factory=list, description="may publish <prefix>/camera/**")
    carms: list[str] = Field(default_factory=list, description="may publish <prefix>/fluoro/shot and <prefix>/fluoro/*/image")
    readers: list[str] | None = Field(None, description="may subscribe; none: any peer that passed TLS or authentication")
    interfaces: list[str] = Field(default_factory=list, description="when set, a name is trusted only on these network interfaces")

    @field_validator("daemon", "cameras", "carms", "readers", "interfaces")
    @classmethod
    def _names(cls, names: list[str] | None) -> list[str] | None:
        for n in names or ():
            if not n or n != n.strip() or len(n) > 64:
                raise ValueError(f"'{n}' is not a usable name (1-64 characters, no surrounding blanks)")
        return names


class ZenohSettings(_Section):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    prefix: str = "drillnav"
    insecure: bool = Field(False, description="accept a bus reachable beyond loopback without TLS, authentication and access control")
    tls: ZenohTlsSettings = Field(default_factory=ZenohTlsSettings)
    auth: ZenohAuthSettings = Field(default_factory=ZenohAuthSettings)
    access_control: ZenohAccessSettings = Field(default_factory=ZenohAccessSettings)

    @model_validator(mode="after")
    def _secure_enough(self) -> "ZenohSettings":
        self.check()
        return self

    def check(self) -> None:
        """Refuse (ValueError naming the key) what cannot work or would expose the bus; see docs/security.md."""
        check_zenoh(self)


class ApiSettings(_Section):
    host: str = "127.0.0.1"
    port: int = Field(8080, ge=1, le=65535)
    # No default: real devices refuse to start without one, the twin makes a random one (service/auth.py resolve_token).
    token: str | None = Field(None, min_length=16, description="bearer token for every changing endpoint (at least 16 characters)")
    tls_cert: Path | None = Field(None, description="PEM certificate (chain) for HTTPS; with tls_key")
    tls_key: Path | None = Field(None, description="PEM private key of tls_cert")
    tls_client_ca: Path | None = Field(None, description="CA whose client certificates are required (mutual TLS); needs tls_cert")
    auth_failures_burst: int = Field(10, ge=1, description="failed authentications from one client within auth_failures_window_s before 429")
    auth_failures_window_s: float = Field(10.0, gt=0)
    max_upload_mb: float = Field(64.0, gt=0, description="largest calibration upload request body")
    max_json_kb: float = Field(64.0, gt=0, description="largest body of any other request")
    max_image_mpixel: float = Field(40.0, gt=0, description="largest uploaded image, checked from its header before decoding")
    max_jobs_running: int = Field(2, ge=1, description="calibration jobs queued or running at once")
    max_jobs_stored: int = Field(50, ge=1, description="calibration jobs kept (finished ones expire sooner)")
    job_expiry_s: float = Field(3600.0, gt=0, description="a finished calibration job is forgotten this long after it ended")
    max_recordings: int = Field(2, ge=1, description="recordings running at once")
    audit_folder: Path = Field(Path("var/audit"), description="audit.jsonl: who changed what (0600 file in a 0700 folder)")

    @model_validator(mode="after")
    def _tls_pairs(self) -> "ApiSettings":
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("api.tls_cert and api.tls_key go together: give both or neither")
        if self.tls_client_ca is not None and self.tls_cert is None:
            raise ValueError("api.tls_client_ca (mutual TLS) needs api.tls_cert and api.tls_key")
        return self


class CameraSettings(_Section):
    device: str = "/dev/video0"
    width: int = 1280
    height: int = 720
    fps: float = Field(30.0, gt=0, le=120)
    fourcc: Literal["MJPG", "YUYV"] = "MJPG"
    exposure: float | None = Field(None, description="V4L2 exposure (driver units); none: the camera's automatic exposure")
    retry_s: float = Field(1.0, gt=0, description="how often a lost camera is reopened")
    calibration: Path | None = None
    drill_calibration: Path | None = None


class DicomSettings(_Section):
    watch_folder: Path = Path("var/incoming")
    scp_enabled: bool = True
    scp_host: str = "127.0.0.1"
    scp_port: int = Field(11112, ge=1, le=65535)
    ae_title: str = Field("DRILLNAV", min_length=1, max_length=16)
    allowed_calling_aes: list[str] | None = None  # None: any calling AE (refused unless the SCP listens on loopback only)
    tls_cert: Path | None = Field(None, description="PEM certificate of the SCP: DICOM over TLS; with tls_key")
    tls_key: Path | None = None
    tls_ca: Path | None = Field(None, description="CA whose client certificates senders must present (mutual TLS)")
    retention_max_age_h: float = Field(24.0, gt=0, description="incoming images older than this are deleted (oldest first)")
    retention_max_mb: float = Field(2048.0, gt=0, description="incoming images beyond this total are deleted, oldest first")
    retention_every_s: float = Field(300.0, gt=0, description="how often the daemon applies the retention")

    @model_validator(mode="after")
    def _safe_listener(self) -> "DicomSettings":
        from drillnav.drivers.dicom_scp import is_loopback

        if self.scp_enabled and self.allowed_calling_aes is None and not is_loopback(self.scp_host):
            raise ValueError(f"dicom.allowed_calling_aes is required when dicom.scp_host ({self.scp_host}) is beyond loopback: name the C-arms' AE titles")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("dicom.tls_cert and dicom.tls_key go together: give both or neither")
        if self.tls_ca is not None and self.tls_cert is None:
            raise ValueError("dicom.tls_ca (mutual TLS) needs dicom.tls_cert and dicom.tls_key")
        return self


class RecordingSettings(_Section):
    folder: Path = Path("var/recordings")
    record_on_start: bool = True
    rotate_mb: int = Field(512, ge=1)
    rotate_minutes: float = Field(60.0, gt=0, description="a new file at least this often")
    # The disk budget (docs/recordings.md): 720p30 camera frames as sent are ~12-16 GB/h; these keep a case under 3 GB/h.
    camera_fps: float = Field(10.0, ge=0, le=120, description="camera frames recorded per second; 0: every frame")
    camera_jpeg_quality: int = Field(75, ge=0, le=100, description="camera frames re-encoded at this JPEG quality; 0: as received")
    overlay_fps: float = Field(0.2, ge=0, le=30, description="overlay JPEGs recorded per second per view (derived: the shots, axes and scene annotations redraw them); 0: every one")
    queue_size: int = Field(256, ge=8, description="messages waiting for the writer thread before new ones are dropped (counted)")
    max_age_days: float = Field(30.0, ge=0, description="retention: finished files older than this are removed at start and each rotation; 0: no age limit")
    max_total_gb: float = Field(50.0, ge=0, description="retention: the oldest finished files are removed while the folder holds more; 0: no cap")
    resume_free_mb: float = Field(64.0, gt=0, description="after a full disk paused recording, free space needed to resume in a new file")


class CalibrationSettings(_Section):
    folder: Path = Path("var/calibration")  # jobs and their results; the active files when camera.* names none


class TwinSettings(_Section):
    seed: int = 0
    markers: int = Field(5, ge=3, le=7)
    views: str = "inlet,outlet"
    ct_voxel_mm: float | None = Field(None, ge=0.5, le=4.0, description="the twin's preoperative CT for the live video-CT mode (voxel size, e.g. 2.0); unset: off")
    # A soak's camera faults, on the daemon's own reconnection path (drivers/sim/devices.py TwinDrillCamera).
    camera_unplug_every_s: float | None = Field(None, gt=0, description="the twin camera's cable is pulled this long after it first opened, and every this long after; unset: never")
    camera_unplug_s: float = Field(3.0, gt=0, description="how long each scheduled unplug lasts (shorter than camera_unplug_every_s)")
    aim_off_mm: float = Field(0.0, ge=0, le=40, description="the twin drill aims this far beside the planned corridor (a breach in the video-CT mode); 0: at it")

    @model_validator(mode="after")
    def _unplug_fits(self) -> "TwinSettings":
        if self.camera_unplug_every_s is not None and self.camera_unplug_s >= self.camera_unplug_every_s:
            raise ValueError(f"twin_scene.camera_unplug_s ({self.camera_unplug_s:g}) must be shorter than camera_unplug_every_s ({self.camera_unplug_every_s:g})")
        return self


class CtSettings(_Section):
    volume: Path | None = None  # preoperative CT: a DICOM series folder or .nii/.nii.gz; enables the live video-CT mode
    plan: Path | None = None    # plan.json: trajectories judged for conformance
    at_mm: tuple[float, float, float] | None = None  # the CT point the C-arm is centred on (default: the plan's first entry)


class RegistrationSettings(_Section):
    # An axis whose predicted error's 90 % bound exceeds either limit is published with reliable = false (displays grey it out).
    unreliable_position_mm: float = Field(3.0, gt=0, description="limit on the 90 % position bound at the working point, mm")
    unreliable_angle_deg: float = Field(3.0, gt=0, description="limit on the 90 % angle bound, degrees")


class IgtlSettings(_Section):
    """OpenIGTLink for 3D Slicer (service/igtl_server.py, docs/slicer.md)."""
    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(18944, ge=1, le=65535, description="18944: OpenIGTLink's registered port, Slicer's default")
    model_start_mm: float = Field(60.0, description="the drill model starts this far along the calibrated axis from its point")
    model_length_mm: float = Field(200.0, gt=0)
    model_radius_mm: float = Field(1.5, gt=0)


class FoxgloveSettings(_Section):
    """Foxglove's schemas on zenoh (service/scene_publisher.py) and the live WebSocket (service/foxglove_bridge.py); docs/foxglove.md."""
    scene: bool = Field(True, description="publish the scene/* topics (so recordings open in Foxglove as a navigation scene)")
    enabled: bool = Field(False, description="serve the live Foxglove WebSocket")
    host: str = "127.0.0.1"
    port: int = Field(8765, ge=1, le=65535)


class Ros2Settings(_Section):
    """The drill axis as geometry_msgs/PoseStamped for rmw_zenoh (service/ros2_bridge.py, docs/ros2.md)."""
    enabled: bool = False
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of the ROS 2 side")
    topic: str = Field("/drillnav/drill_axis", pattern=r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
    node: str = Field("drillnav", pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="DRILLNAV_", env_nested_delimiter="__", extra="forbid")
    twin: bool = False
    markers_file: Path | None = None
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    api: ApiSettings = Field(default_factory=ApiSettings)
    camera: CameraSettings = Field(default_factory=CameraSettings)
    dicom: DicomSettings = Field(default_factory=DicomSettings)
    recording: RecordingSettings = Field(default_factory=RecordingSettings)
    twin_scene: TwinSettings = Field(default_factory=TwinSettings)
    calibration: CalibrationSettings = Field(default_factory=CalibrationSettings)
    ct: CtSettings = Field(default_factory=CtSettings)
    registration: RegistrationSettings = Field(default_factory=RegistrationSettings)
    igtl: IgtlSettings = Field(default_factory=IgtlSettings)
    foxglove: FoxgloveSettings = Field(default_factory=FoxgloveSettings)
    ros2: Ros2Settings = Field(default_factory=Ros2Settings)

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings], init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource, dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource) -> tuple[PydanticBaseSettingsSource, ...]:
        # The file's values as a source below the environment: given as constructor arguments they would beat it
        # (pydantic-settings ranks init arguments first), and an operator's DRILLNAV_* override would be silently ignored.
        return init_settings, env_settings, InitSettingsSource(settings_cls, init_kwargs=_FILE_VALUES.get())


# The config file's values while load_settings builds a Settings (read by settings_customise_sources).
_FILE_VALUES: ContextVar[dict] = ContextVar("drillnav_settings_file_values", default={})


class SettingsError(DrillnavError):
    """A configuration that cannot be used; the message names the field."""


def load_settings(config: Path | None = None, **overrides) -> Settings:
    data: dict = {}
    if config is not None:
        try:
            data = tomllib.loads(Path(config).read_text())
        except FileNotFoundError:
            raise SettingsError(f"config file {config} does not exist") from None
        except tomllib.TOMLDecodeError as exc:
            raise SettingsError(f"{config}: not valid TOML ({exc})") from None
    token = _FILE_VALUES.set(data)
    try:
        return Settings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        raise SettingsError(describe_validation_error(exc)) from None
    finally:
        _FILE_VALUES.reset(token)


def describe_validation_error(exc: ValidationError, *, prefix: str = "") -> str:
    """One line naming the first refused setting (``zenoh.tls.ca``) and why."""
    first = exc.errors()[0]
    where = ".".join(str(p) for p in (prefix, *first["loc"]) if p != "")
    why = first["msg"].removeprefix("Value error, ")
    return f"invalid setting '{where}': {why} ({len(exc.errors())} problem(s) in all)"
