"""The daemon's settings: one object, from a TOML file and DRILLNAV_* environment variables.

Environment wins over the file (``DRILLNAV_API__PORT=8081``). Unknown keys and
invalid values are refused with the field named: a medical device must not
silently replace a bad setting with a default.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

from drillnav.registration.errors import DrillnavError

__all__ = ["Settings", "SettingsError", "load_settings"]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ZenohSettings(_Section):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    prefix: str = "drillnav"


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
    igtl: IgtlSettings = Field(default_factory=IgtlSettings)
    foxglove: FoxgloveSettings = Field(default_factory=FoxgloveSettings)
    ros2: Ros2Settings = Field(default_factory=Ros2Settings)


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
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise SettingsError(f"invalid setting '{where}': {first['msg']} ({len(exc.errors())} problem(s) in all)") from None
