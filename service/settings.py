"""The daemon's settings: one object, from a TOML file and DRILLNAV_* environment variables.

Environment wins over the file (``DRILLNAV_API__PORT=8081``). Unknown keys and
invalid values are refused with the field named: a medical device must not
silently replace a bad setting with a default.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

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
    token: str = Field("change-me", min_length=8, description="bearer token for every changing endpoint")


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
    allowed_calling_aes: list[str] | None = None  # None: any calling AE


class RecordingSettings(_Section):
    folder: Path = Path("var/recordings")
    record_on_start: bool = True
    rotate_mb: int = Field(512, ge=1)
    rotate_minutes: float = Field(60.0, gt=0, description="a new file at least this often")


class CalibrationSettings(_Section):
    folder: Path = Path("var/calibration")  # jobs and their results; the active files when camera.* names none


class TwinSettings(_Section):
    seed: int = 0
    markers: int = Field(5, ge=3, le=7)
    views: str = "inlet,outlet"
    ct_voxel_mm: float | None = Field(None, ge=0.5, le=4.0, description="the twin's preoperative CT for the live video-CT mode (voxel size, e.g. 2.0); unset: off")


class CtSettings(_Section):
    volume: Path | None = None  # preoperative CT: a DICOM series folder or .nii/.nii.gz; enables the live video-CT mode
    plan: Path | None = None    # plan.json: trajectories judged for conformance
    at_mm: tuple[float, float, float] | None = None  # the CT point the C-arm is centred on (default: the plan's first entry)


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
    data.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return Settings(**data)
    except ValidationError as exc:
        raise SettingsError(describe_validation_error(exc)) from None


def describe_validation_error(exc: ValidationError, *, prefix: str = "") -> str:
    """One line naming the first refused setting (``zenoh.tls.ca``) and why."""
    first = exc.errors()[0]
    where = ".".join(str(p) for p in (prefix, *first["loc"]) if p != "")
    why = first["msg"].removeprefix("Value error, ")
    return f"invalid setting '{where}': {why} ({len(exc.errors())} problem(s) in all)"
