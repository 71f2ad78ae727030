"""Bench configuration (TOML) and the URI -> backend factory.

A bench file names its devices by URI; device code never asks whether it is simulated::

    [actuators]
    uri = "modbus+tcp://127.0.0.1:5020"     # modbus+rtu:///dev/ttyUSB0?baudrate=115200,
                                            # modbus+rtu+tcp://HOST:PORT, serial:///dev/ttyACM0
    axes = 4                                # optional: number of axes (4, the I4's, by default; Modbus only)
    speed_m_s = 0.05
    [actuators.limits]
    q_min = [-0.1, -0.1, -0.1, -0.1]
    q_max = [0.8, 0.8, 0.8, 0.8]
    [actuators.register_map]                # overrides of drivers.devices.registermap.RegisterMap
    word_order = "big"
    [camera]
    uri = "genicam://?cti=/opt/vendor/x.cti&serial=SN"   # v4l2:///dev/video0, replay://DATASET, sim://HOST:PORT
    lens_model = "k1k2k3"                   # optional: fixes the calibration's lens model (default: auto)
    intrinsics = "camera.json"              # optional: the camera's intrinsics (`i4cal camera calibrate`), relative
                                            # to this file; acquire records them in every dataset
    [operator]
    uri = "console"                         # or sim://HOST:PORT (the simulated operator)
    [nominal]
    file = "nominal.json"                   # optional: the a priori geometry; default calib.model.parameters.NOMINAL
    [suspenders]                            # optional: pause while the image is dark / the board unseen
    enabled = true                          # (drivers.acquisition.suspenders: every setting and its default)

Each URI scheme has a factory in a registry (:func:`register_actuators_scheme`, :func:`register_camera_scheme`,
:func:`register_operator_scheme`) that :func:`open_actuators`, :func:`open_camera` and :func:`open_operator` use; a
factory imports its backend only when a URI of its scheme is opened, so the simulated devices' clients
(``sim://``, :mod:`drivers.devices.cameras.sim`) and vendor libraries are loaded only when a bench file names them. An
unknown scheme raises :class:`calib.errors.InputError` naming the URI and the known schemes.

Vendor libraries are optional: a missing one raises :class:`drivers.errors.MissingExtraError` naming the
extra to install.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple
from urllib.parse import parse_qs, unquote, urlsplit

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from calib.errors import InputError
from calib.model.parameters import NOMINAL, I4Parameters
from drivers.acquisition.suspenders import SuspendersConfig
from drivers.devices.interfaces import Actuators, Camera, Operator, SoftLimitsM
from drivers.devices.registermap import RegisterMap

if TYPE_CHECKING:
    from calib.formats.camera import CameraModel


class LimitsConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    q_min: list[float] = Field(default_factory=lambda: [-0.10] * 4, min_length=1, max_length=16)
    q_max: list[float] = Field(default_factory=lambda: [0.80] * 4, min_length=1, max_length=16)


class ActuatorsConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    uri: str
    axes: int = Field(
        4,
        ge=1,
        le=16,
        description="number of linear axes (4: the I4); the register map's default axes are units 1..axes, the "
        "default soft limits one value per axis; explicit ones must have as many",
    )
    speed_m_s: float = Field(0.05, gt=0)
    accel_m_s2: float = Field(0.5, gt=0)
    timeout_s: float = Field(0.5, gt=0, description="reply timeout of one request")
    retries: int = Field(3, ge=0)
    poll_s: float = Field(0.002, ge=0)
    settle_s: float = Field(0.0, ge=0)
    in_position_m: float = Field(2e-5, gt=0)
    home_timeout_s: float = Field(60.0, gt=0)
    home_on_connect: bool = Field(True, description="home the axes before a run when they are not homed")
    stop_deadline_s: float = Field(2.0, gt=0, description="one deadline for a stop: sent and read back stopped")
    late_reply_guard_s: float | None = Field(
        None, ge=0, description="RTU framing: link kept closed after a fault (s); default 2 x timeout_s"
    )
    max_speed_m_s: float | None = Field(
        None, gt=0, description="fastest an axis can move, for plausible readings; default 5 x speed_m_s"
    )
    plausibility_margin_m: float = Field(0.05, ge=0, description="readings beyond the soft limits by more: refused")
    vary_reads: bool = Field(
        True, description="read through varied register windows so a stale reply has the wrong length"
    )
    duplicate_window_s: float = Field(
        0.06, ge=0, description="a reply may be duplicated this long after it came: its shape is not asked meanwhile"
    )
    motion_confirm_s: float | None = Field(
        None,
        gt=0,
        description="an unanswered motion command's state is read back on its connection this long; default 4 x "
        "the reply timeout",
    )
    watchdog_s: float = Field(
        0.5, ge=0, description="the drives' communication watchdog (0: none); the reply timeout is capped below it"
    )
    stop_persist_s: float = Field(
        30.0, ge=0, description="a failed run keeps stopping this long while the controller is connected but silent"
    )
    max_accel_m_s2: float | None = Field(
        None, gt=0, description="fastest an axis accelerates, for plausible readings; default: not bounded"
    )
    limits: LimitsConfig = LimitsConfig()
    register_map: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _axis_count(self) -> ActuatorsConfig:
        n = self.axes
        lim = self.limits
        values = {}
        for key in ("q_min", "q_max"):
            v = list(getattr(lim, key))
            if key not in lim.model_fields_set and len(v) != n:
                v = [v[0]] * n  # the default value on every axis
            elif len(v) != n:
                raise ValueError(f"limits.{key} has {len(v)} values for {n} axes (actuators.axes)")
            values[key] = v
        if n != 4:
            self.limits = LimitsConfig(**values)
        axes = self.register_map.get("axes")
        if isinstance(axes, list) and len(axes) != n:
            raise ValueError(f"register_map.axes lists {len(axes)} axes for {n} (actuators.axes)")
        return self


class CameraMountingConfig(BaseModel):
    """Where the camera sits on the bench: its frame (OpenCV's: x right, y down, z along the optical axis) in the
    robot's base frame, ``p_base = R(rotation_rad) p_camera + position_m`` (``rotation_rad`` a rotation vector).
    What experiment design places the camera by (``i4cal plan design`` / ``plan predict``)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    position_m: list[float] = Field(min_length=3, max_length=3, description="the camera centre in the base frame, m")
    rotation_rad: list[float] = Field(
        min_length=3, max_length=3, description="rotation vector of the camera's axes in the base frame, rad"
    )

    @field_validator("position_m", "rotation_rad")
    @classmethod
    def _finite(cls, v: list[float]) -> list[float]:
        if not np.all(np.isfinite(v)):
            raise ValueError("must be finite")
        return v


class CameraConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    uri: str
    timeout_s: float = Field(2.0, gt=0)
    exposure_us: float | None = None
    gain_db: float | None = None
    pixel_format: str | None = None
    width: int | None = None
    height: int | None = None
    grab_retries: int = Field(1, ge=0, description="grabs retried after a timeout or a corrupt frame")
    lens_model: str | None = Field(
        None,
        description="lens model of the camera calibration (calib.camera.intrinsics.LENS_MODEL_CHOICES: auto, "
        "k1k2, k1k2k3, rational[-radial]); recorded in the dataset's camera section, which extraction follows",
    )
    intrinsics: str | None = Field(
        None,
        description="the camera's intrinsics: an i4cal.camera/1 file (written by `i4cal camera calibrate`, "
        "docs/camera.md), relative to the bench file; acquire records them (and the file's SHA-256) in the dataset",
    )
    mounting: CameraMountingConfig | None = Field(
        None, description="the camera's pose in the robot's base frame (experiment design); default: not given"
    )

    @field_validator("lens_model")
    @classmethod
    def _lens_model(cls, v: str | None) -> str | None:
        from calib.camera.intrinsics import LENS_MODEL_CHOICES

        if v is not None and v not in LENS_MODEL_CHOICES:
            raise ValueError(f"unknown lens model {v!r}; lens models are {', '.join(LENS_MODEL_CHOICES)}")
        return v


class IntrinsicsFile(NamedTuple):
    """The camera file a bench file names (``[camera] intrinsics``): its model, where it is and its SHA-256."""

    camera: CameraModel
    path: Path
    sha256: str


class OperatorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    uri: str = "console"


class AcquisitionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    line_rate_hz: float | None = Field(None, gt=0, description="override the plan's guided-line sampling rate")
    settle_s: float = Field(0.0, ge=0)


class NominalConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    file: str | None = None


class BenchConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    name: str = "bench"
    actuators: ActuatorsConfig
    camera: CameraConfig
    operator: OperatorConfig = OperatorConfig()
    acquisition: AcquisitionConfig = AcquisitionConfig()
    nominal: NominalConfig = NominalConfig()
    suspenders: SuspendersConfig = SuspendersConfig()
    source: str | None = Field(None, exclude=True)

    def soft_limits(self) -> SoftLimitsM:
        lim = self.actuators.limits
        return SoftLimitsM(tuple(lim.q_min), tuple(lim.q_max))

    def calib_limits(self):
        from calib.formats.plan import SoftLimits

        return SoftLimits(q_min=self.actuators.limits.q_min, q_max=self.actuators.limits.q_max)

    def nominal_parameters(self) -> I4Parameters:
        if not self.nominal.file:
            return NOMINAL
        path = Path(self.nominal.file)
        if self.source and not path.is_absolute():
            path = Path(self.source).parent / path
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError("nominal geometry file not found", file=str(path)) from None
        except json.JSONDecodeError as exc:
            raise InputError(f"not valid JSON: {exc.msg}", file=str(path)) from None
        for key in ("parameters", "nominal"):
            if isinstance(data, dict) and isinstance(data.get(key), dict):
                data = data[key]
        try:
            return I4Parameters.from_mapping(data)
        except (ValueError, TypeError) as exc:
            raise InputError(str(exc), file=str(path)) from None

    def intrinsics_path(self) -> Path | None:
        """The camera file named by ``[camera] intrinsics`` (relative to the bench file), or None."""
        if not self.camera.intrinsics:
            return None
        path = Path(self.camera.intrinsics)
        if self.source and not path.is_absolute():
            path = Path(self.source).parent / path
        return path

    def camera_intrinsics(self) -> IntrinsicsFile | None:
        """The camera file named by ``[camera] intrinsics``, read and checked, or None when the bench names none.

        Raises
        ------
        InputError
            The file is missing, not JSON, not ``i4cal.camera/1`` or not a camera model; the message names the
            bench file's field and the camera file, and the command that writes one.
        """
        from calib.formats.camera import CAMERA_FORMAT, CameraModel

        path = self.intrinsics_path()
        if path is None:
            return None
        where = f"{self.source}, field 'camera.intrinsics'" if self.source else "field 'camera.intrinsics'"
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            raise InputError(
                f"camera file not found ({where}); write it with `i4cal camera calibrate --bench "
                f"{self.source or 'BENCH'} -o {self.camera.intrinsics}`",
                file=str(path),
            ) from None
        except OSError as exc:
            raise InputError(f"cannot read the camera file ({where}): {exc.strerror}", file=str(path)) from None
        try:
            data = json.loads(raw)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"not valid JSON ({where}): {exc}", file=str(path)) from None
        if not isinstance(data, dict) or data.get("format") != CAMERA_FORMAT:
            got = data.get("format") if isinstance(data, dict) else None
            raise InputError(
                f"not a camera file ({where}): format {got!r}, expected {CAMERA_FORMAT!r}",
                file=str(path),
                field="format",
            )
        camera = CameraModel.from_dict(data, source=str(path))
        return IntrinsicsFile(camera, path, hashlib.sha256(raw).hexdigest())

    def register_map(self) -> RegisterMap:
        data = dict(self.actuators.register_map)
        data.setdefault("axes", [{"unit": i + 1, "offset": 0} for i in range(self.actuators.axes)])
        try:
            return RegisterMap.model_validate(data)
        except ValidationError as exc:
            err = exc.errors()[0]
            raise InputError(
                err["msg"], file=self.source, field="actuators.register_map." + ".".join(map(str, err["loc"]))
            ) from None


def load_bench(path: str | Path) -> BenchConfig:
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("bench file not found", file=str(p)) from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", file=str(p)) from None
    try:
        cfg = BenchConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise InputError(err["msg"], file=str(p), field=".".join(map(str, err["loc"]))) from None
    cfg.source = str(p)
    return cfg


# -- URIs and the scheme registry ----------------------------------------------------------------------------------
def parse_uri(uri: str) -> tuple[str, str, int | None, str, dict[str, str]]:
    """``(scheme, host, port, path, query)`` of a device URI."""
    parts = urlsplit(uri)
    if not parts.scheme:
        raise InputError(f"device URI {uri!r} has no scheme (e.g. modbus+tcp://127.0.0.1:5020)", field="uri")
    query = {k: v[-1] for k, v in parse_qs(parts.query).items()}
    try:
        port = parts.port
    except ValueError:
        raise InputError(f"bad port in device URI {uri!r}", field="uri") from None
    return parts.scheme.lower(), parts.hostname or "", port, unquote(parts.path), query


class DeviceURI(NamedTuple):
    """A device URI as the backend factories get it (:func:`parse_uri`'s parts and the text)."""

    text: str
    scheme: str
    host: str
    port: int | None
    path: str
    query: dict[str, str]

    @classmethod
    def parse(cls, uri: str) -> DeviceURI:
        return cls(uri, *parse_uri(uri))


WorkspaceCheck = Callable[[np.ndarray], Any]
#: ``factory(bench, uri, workspace_check) -> Actuators`` (not yet connected)
ActuatorsFactory = Callable[[BenchConfig, DeviceURI, WorkspaceCheck | None], Actuators]
#: ``factory(camera_section, uri) -> Camera`` (not yet opened)
CameraFactory = Callable[[CameraConfig, DeviceURI], Camera]
#: ``factory(bench, uri) -> Operator``
OperatorFactory = Callable[[BenchConfig, DeviceURI], Operator]


class _Registry:
    """URI scheme -> backend factory, for one kind of device. A factory is a callable, or ``"module:attribute"``
    naming one, imported when a URI of its scheme is first opened (the backend's module, and what it imports, only
    then: e.g. a simulated device's)."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._factories: dict[str, Any] = {}

    def register(self, scheme: str, factory: Any, *, replace: bool = False) -> None:
        key = scheme.lower()
        if not key or "://" in key or ":" in key:
            raise ValueError(f"{self.kind} URI scheme {scheme!r}: a scheme is the part before '://', e.g. 'modbus+tcp'")
        if not (callable(factory) or (isinstance(factory, str) and ":" in factory)):
            raise TypeError(f"{self.kind} scheme {scheme!r}: the factory must be callable or 'module:attribute'")
        if key in self._factories and not replace and self._factories[key] is not factory:
            raise ValueError(f"{self.kind} URI scheme {key!r} is already registered (pass replace=True to replace it)")
        self._factories[key] = factory

    def schemes(self) -> tuple[str, ...]:
        return tuple(self._factories)

    def get(self, scheme: str) -> Any | None:
        factory = self._factories.get(scheme)
        if isinstance(factory, str):
            module, _, attr = factory.partition(":")
            try:
                factory = getattr(importlib.import_module(module), attr)
            except (ImportError, AttributeError) as exc:
                raise InputError(
                    f"{self.kind} URI scheme {scheme!r}: cannot load its backend {self._factories[scheme]!r} ({exc})",
                    field=f"{self.kind}.uri",
                ) from None
            self._factories[scheme] = factory
        return factory


_ACTUATORS = _Registry("actuators")
_CAMERAS = _Registry("camera")
_OPERATORS = _Registry("operator")


def register_actuators_scheme(scheme: str, factory: ActuatorsFactory | str, *, replace: bool = False) -> None:
    """Open actuators URIs ``scheme://...`` with ``factory(bench, uri, workspace_check)``.

    ``factory``: a callable (:data:`ActuatorsFactory`) or ``"module:attribute"`` naming one, imported when such a URI
    is first opened. A scheme already registered raises :class:`ValueError` unless ``replace``.
    """
    _ACTUATORS.register(scheme, factory, replace=replace)


def register_camera_scheme(scheme: str, factory: CameraFactory | str, *, replace: bool = False) -> None:
    """Open camera URIs ``scheme://...`` with ``factory(camera_config, uri)`` (as :func:`register_actuators_scheme`)."""
    _CAMERAS.register(scheme, factory, replace=replace)


def register_operator_scheme(scheme: str, factory: OperatorFactory | str, *, replace: bool = False) -> None:
    """Open operator URIs ``scheme://...`` with ``factory(bench, uri)`` (as :func:`register_actuators_scheme`)."""
    _OPERATORS.register(scheme, factory, replace=replace)


def actuators_schemes() -> tuple[str, ...]:
    """The registered actuators URI schemes, in registration order."""
    return _ACTUATORS.schemes()


def camera_schemes() -> tuple[str, ...]:
    """The registered camera URI schemes, in registration order."""
    return _CAMERAS.schemes()


def operator_schemes() -> tuple[str, ...]:
    """The registered operator URI schemes, in registration order (``console`` is also written without ``://``)."""
    return _OPERATORS.schemes()


def open_actuators(cfg: BenchConfig, *, workspace_check: WorkspaceCheck | None = None) -> Actuators:
    """The actuators backend named by ``cfg.actuators.uri`` (not yet connected), by its scheme's factory.

    ``workspace_check``: refuses joint targets outside a workspace (raises
    :class:`calib.errors.UnreachableError`; e.g. ``lambda q: delta.dkm(nominal, q)``); default: the nominal I4's
    DKM, used with four axes only.
    """
    uri = DeviceURI.parse(cfg.actuators.uri)
    factory = _ACTUATORS.get(uri.scheme)
    if factory is None:
        raise InputError(
            f"unknown actuators URI scheme {uri.scheme!r} in {uri.text!r} ({', '.join(actuators_schemes())})",
            field="actuators.uri",
        )
    actuators: Actuators = factory(cfg, uri, workspace_check)
    return actuators


def open_camera(cfg: BenchConfig | CameraConfig | str) -> Camera:
    """The camera backend named by a URI (not yet opened), by its scheme's factory."""
    c = (
        cfg.camera
        if isinstance(cfg, BenchConfig)
        else (cfg if isinstance(cfg, CameraConfig) else CameraConfig(uri=cfg))
    )
    uri = DeviceURI.parse(c.uri)
    factory = _CAMERAS.get(uri.scheme)
    if factory is None:
        raise InputError(
            f"unknown camera URI scheme {uri.scheme!r} in {uri.text!r} ({', '.join(camera_schemes())})",
            field="camera.uri",
        )
    camera: Camera = factory(c, uri)
    return camera


def open_operator(cfg: BenchConfig) -> Operator:
    """Who guides the end-effector during a line step, named by ``cfg.operator.uri``, by its scheme's factory."""
    text = cfg.operator.uri
    uri = DeviceURI(text, "console", "", None, "", {}) if text == "console" else DeviceURI.parse(text)
    factory = _OPERATORS.get(uri.scheme)
    if factory is None:
        raise InputError(f"unknown operator URI {text!r} ({', '.join(operator_schemes())})", field="operator.uri")
    operator: Operator = factory(cfg, uri)
    return operator


# -- the built-in backends: each imports its module only when a URI of its scheme is opened -----------------------
def _modbus_actuators(cfg: BenchConfig, uri: DeviceURI, workspace_check: WorkspaceCheck | None) -> Actuators:
    from drivers.devices.axes import AxisSettings
    from drivers.devices.modbus import ModbusActuators, ModbusLinkSettings

    a = cfg.actuators
    common = _common_actuators(cfg)
    link = ModbusLinkSettings(
        regmap=cfg.register_map(),
        timeout_s=float(uri.query.get("timeout", a.timeout_s)),
        retries=a.retries,
        late_reply_guard_s=a.late_reply_guard_s,
        vary_reads=a.vary_reads,
    )
    axes = AxisSettings(
        speed_m_s=a.speed_m_s,
        accel_m_s2=a.accel_m_s2,
        poll_s=a.poll_s,
        settle_s=a.settle_s,
        in_position_m=a.in_position_m,
        home_timeout_s=a.home_timeout_s,
        stop_deadline_s=a.stop_deadline_s,
        max_speed_m_s=a.max_speed_m_s,
        plausibility_margin_m=a.plausibility_margin_m,
    )
    safety = safety_settings(a)
    if uri.scheme == "modbus+rtu":
        if not uri.path:
            raise InputError(
                f"{uri.text!r}: a serial device path is needed, e.g. modbus+rtu:///dev/ttyUSB0", field="actuators.uri"
            )
        link = dataclasses.replace(
            link, transport="rtu", serial_port=uri.path, baudrate=int(uri.query.get("baudrate", 115200))
        )
    else:
        transport = "rtu-tcp" if uri.scheme == "modbus+rtu+tcp" else "tcp"
        link = dataclasses.replace(link, transport=transport, host=uri.host or "127.0.0.1", port=uri.port or 502)
    return ModbusActuators(link, axes, workspace_check=workspace_check, safety=safety, **common)


def safety_settings(a: ActuatorsConfig) -> Any:
    """The ``[actuators]`` motion-safety keys as :class:`drivers.devices.links.SafetySettings`."""
    from drivers.devices.links import SafetySettings

    return SafetySettings(
        duplicate_window_s=a.duplicate_window_s,
        motion_confirm_s=a.motion_confirm_s,
        watchdog_s=a.watchdog_s,
        stop_persist_s=a.stop_persist_s,
        max_accel_m_s2=a.max_accel_m_s2,
    )


def _common_actuators(cfg: BenchConfig) -> dict[str, Any]:
    # the nominal I4 checks the targets of four axes; with other axes, ``workspace_check`` when given
    a = cfg.actuators
    return dict(limits=cfg.soft_limits(), nominal=cfg.nominal_parameters() if a.axes == 4 else None)


def _serial_ascii_actuators(cfg: BenchConfig, uri: DeviceURI, workspace_check: WorkspaceCheck | None) -> Actuators:
    from drivers.devices.serial_ascii import SerialAsciiActuators

    a = cfg.actuators
    common = _common_actuators(cfg)
    if a.axes != 4 or workspace_check is not None:
        raise InputError(
            f"{uri.text!r}: the serial ASCII protocol drives four axes with the I4's nominal check "
            f"(actuators.axes = {a.axes}); use a Modbus URI",
            field="actuators.axes",
        )
    url = f"socket://{uri.host}:{uri.port}" if uri.scheme == "serial+tcp" else uri.path
    if not url:
        raise InputError(
            f"{uri.text!r}: a serial device path is needed, e.g. serial:///dev/ttyACM0", field="actuators.uri"
        )
    return SerialAsciiActuators(
        url,
        baudrate=int(uri.query.get("baudrate", 115200)),
        timeout_s=float(uri.query.get("timeout", a.timeout_s)),
        speed_m_s=a.speed_m_s,
        accel_m_s2=a.accel_m_s2,
        poll_s=max(a.poll_s, 0.001),
        retries=a.retries,
        in_position_m=a.in_position_m,
        home_timeout_s=a.home_timeout_s,
        stop_deadline_s=a.stop_deadline_s,
        max_speed_m_s=a.max_speed_m_s,
        plausibility_margin_m=a.plausibility_margin_m,
        safety=safety_settings(a),
        **common,
    )


def _sim_camera(c: CameraConfig, uri: DeviceURI) -> Camera:
    from drivers.devices.cameras.sim import (
        SimCamera,  # the client of the simulated bench's endpoint: it never imports drivers.sim
    )

    if not uri.host or not uri.port:
        raise InputError(
            f"{uri.text!r}: sim cameras are served by a simulated bench: sim://HOST:PORT (run `i4cal sim-bench`)",
            field="camera.uri",
        )
    return SimCamera(uri.host, uri.port, timeout_s=c.timeout_s)


def _genicam_camera(c: CameraConfig, uri: DeviceURI) -> Camera:
    from drivers.devices.cameras.genicam import GenICamCamera

    return GenICamCamera(cti=uri.query.get("cti"), serial=uri.query.get("serial"), timeout_s=c.timeout_s)


def _v4l2_camera(c: CameraConfig, uri: DeviceURI) -> Camera:
    from drivers.devices.cameras.v4l2 import V4L2Camera

    dev: str | int = (uri.host + uri.path) if uri.host else uri.path
    if isinstance(dev, str) and dev.isdigit():
        dev = int(dev)
    return V4L2Camera(dev, timeout_s=c.timeout_s)


def _replay_camera(c: CameraConfig, uri: DeviceURI) -> Camera:
    from drivers.devices.cameras.replay import ReplayCamera

    return ReplayCamera(uri.host + uri.path if uri.host else uri.path, loop=uri.query.get("loop", "0") in ("1", "true"))


def _console_operator(cfg: BenchConfig, uri: DeviceURI) -> Operator:
    from drivers.acquisition.operators import ConsoleOperator

    return ConsoleOperator()


def _sim_operator(cfg: BenchConfig, uri: DeviceURI) -> Operator:
    from drivers.devices.cameras.sim import SimOperator

    if uri.port is None:
        raise InputError(f"operator URI {uri.text!r} needs a port (sim://HOST:PORT)", field="operator.uri")
    return SimOperator(uri.host, uri.port)


for _scheme in ("modbus+tcp", "modbus+rtu", "modbus+rtu+tcp"):
    register_actuators_scheme(_scheme, _modbus_actuators)
for _scheme in ("serial", "serial+tcp"):
    register_actuators_scheme(_scheme, _serial_ascii_actuators)
register_actuators_scheme("modbus", _modbus_actuators)  # Modbus TCP
register_camera_scheme("genicam", _genicam_camera)
register_camera_scheme("v4l2", _v4l2_camera)
register_camera_scheme("replay", _replay_camera)
register_camera_scheme("sim", _sim_camera)
register_operator_scheme("console", _console_operator)
register_operator_scheme("sim", _sim_operator)
