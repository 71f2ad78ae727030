"""Service settings (pydantic-settings): a TOML file, then ``I4CAL_*`` environment variables on top.

::

    data_dir = "/var/lib/i4cal"          # database (SQLite, WAL), datasets, results
    database_url = ""                    # default sqlite:///<data_dir>/i4cal.db; postgresql+psycopg://... accepted
    host = "127.0.0.1"
    port = 8000
    bench_file = "deploy/bench-sim.toml" # the bench this service drives (or sim_bench = true)
    sim_bench = false                    # start a simulated bench (its own process) on loopback
    open_reads = true                    # GET endpoints without a token
    token_hashes = []                    # sha256 hex of accepted bearer tokens (`i4cal token create` stores more)
    allowed_hosts = ["127.0.0.1", "localhost", "[::1]"]  # Host header values answered (+ host if one address)
    data_quota_bytes = 68719476736       # 64 GiB under data_dir at most (0: no quota); 507 beyond
    min_free_bytes = 1073741824          # 1 GiB always left free on the data disk; 507 beyond
    [check_schedule]                     # optional: scheduled checks (docs/check.md)
    every_hours = 24                     # and/or idle_minutes = 30
    action = "propose"                   # record, propose, notify (with notify_url = "https://...")

Environment: ``I4CAL_DATA_DIR``, ``I4CAL_PORT``, ``I4CAL_OPEN_READS``, ... (nested: ``I4CAL_PLAN_SIZES__N_FIT``).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, field_validator, model_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from calib.errors import InputError

#: A bench name: 1-64 letters, digits, spaces, '.', '_' or '-' (it names calibrations and runs, in URLs too).
BENCH_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9 ._-]{0,63}$"


def default_data_dir() -> Path:
    """The platform's user data directory for i4cal: ``$XDG_DATA_HOME/i4cal`` (default ``~/.local/share/i4cal``) on
    Linux and other Unix systems, ``~/Library/Application Support/i4cal`` on macOS, ``%LOCALAPPDATA%\\i4cal`` on
    Windows (platformdirs' ``user_data_dir`` when it is installed). Never inside the checkout: a read-only checkout or
    an installed package keeps working."""
    import os
    import sys

    try:
        import platformdirs
    except ImportError:
        platformdirs = None
    if platformdirs is not None:
        return Path(platformdirs.user_data_dir("i4cal", appauthor=False))
    if sys.platform == "win32":
        return Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local") / "i4cal"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Application Support" / "i4cal"
    xdg = os.environ.get("XDG_DATA_HOME", "")
    return (Path(xdg) if os.path.isabs(xdg) else Path.home() / ".local" / "share") / "i4cal"


class PlanSizes(BaseModel):
    """Sizes of the named plans the service generates (``calib.formats.plan.make_plan`` keywords)."""

    n_base: int = Field(10, ge=3, le=500)
    n_fit: int = Field(20, ge=3, le=2000)
    n_lock: int = Field(5, ge=1, le=500)
    n_validation: int = Field(10, ge=1, le=2000)
    line_samples: int = Field(51, ge=3, le=5000)
    seed: int = 0


class CheckSchedule(BaseModel):
    """Scheduled checks (``[check_schedule]`` in the service's TOML; :mod:`service.checks.schedule`, docs/check.md)."""

    every_hours: float | None = Field(None, gt=0, description="a check this long after the last scheduled one, h")
    idle_minutes: float | None = Field(
        None, gt=0, description="a check once no run has held the bench for this long (once per idle period), min"
    )
    action: Literal["record", "propose", "notify"] = Field(
        "record",
        description="record: store the check only; propose: store it with its proposed update; notify: as propose, "
        "and POST its summary to notify_url",
    )
    notify_url: str | None = Field(None, description="the webhook the 'notify' action POSTs JSON to (http, https)")
    max_seconds: float = Field(60.0, gt=0, description="motion budget of the designed check plan, s")
    alpha: float = Field(0.05, gt=0, lt=0.5, description="false-alarm probability when nothing drifted")
    poll_s: float = Field(30.0, gt=0, le=3600, description="how often the scheduler looks whether a check is due, s")

    @model_validator(mode="after")
    def _complete(self) -> CheckSchedule:
        if self.every_hours is None and self.idle_minutes is None:
            raise ValueError("check_schedule needs every_hours or idle_minutes")
        if self.action == "notify" and not (self.notify_url or "").startswith(("http://", "https://")):
            raise ValueError("the action 'notify' needs notify_url, an http:// or https:// URL")
        return self


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="I4CAL_", env_nested_delimiter="__", extra="forbid")

    data_dir: Path = Field(
        default_factory=lambda: default_data_dir(),
        description="database, datasets and results live here (default: the user's data directory, "
        "$XDG_DATA_HOME/i4cal or ~/.local/share/i4cal on Linux)",
    )
    database_url: str | None = Field(
        None,
        description="SQLAlchemy URL: sqlite:///PATH or "
        "postgresql+psycopg://USER:PASSWORD@HOST:PORT/DB (postgresql:// is taken as "
        "psycopg; needs the 'postgres' extra); default SQLite in data_dir",
    )
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    bench_name: str | None = Field(
        None,
        pattern=BENCH_NAME_PATTERN,
        description="this bench's name (default: the bench file's name); services sharing "
        "a database must have different names",
    )
    bench_file: Path | None = Field(None, description="bench TOML (drivers.acquisition.config)")
    bench: dict[str, Any] | None = Field(None, description="inline bench configuration (same fields as the TOML)")
    sim_bench: bool = Field(False, description="start a simulated bench (in its own process) and drive it")
    sim_port: int = Field(0, ge=0, le=65535, description="simulated bench base port (0: free ports)")
    sim_fast_renderer: bool = Field(False, description="simulated frames without the image-level twin")
    camera_file: Path | None = Field(None, description="known intrinsics (i4cal.camera/1 JSON) for extraction")
    open_reads: bool = Field(True, description="GET endpoints answer without a token")
    token_hashes: list[str] = Field(default_factory=list, description="sha256 hex digests of accepted tokens")
    max_upload_bytes: int = Field(512 * 1024 * 1024, gt=0, description="largest upload (the archive as sent), 413")
    max_unpacked_bytes: int = Field(
        4 * 1024 * 1024 * 1024,
        gt=0,
        description="most bytes one upload may unpack to, counted as they are written (422 naming it)",
    )
    data_quota_bytes: int = Field(
        64 * 1024**3,
        ge=0,
        description="most bytes under data_dir (database, runs, datasets, temporary files), counted as written: an "
        "upload or a run that would pass it is refused (507 naming it); 0: no quota, only the disk's free space",
    )
    min_free_bytes: int = Field(
        1024**3,
        ge=0,
        description="free space always left on the data disk: a run or an upload that would leave less is refused "
        "(507 naming it)",
    )
    run_space_margin: float = Field(
        1.5,
        ge=1.0,
        le=10.0,
        description="a run starts only if the frames still to acquire, times the frame's expected size, times this "
        "margin, fit in the quota and the free space",
    )
    frame_bytes: int | None = Field(
        None,
        gt=0,
        description="expected bytes of one frame on disk (default: the camera's width x height x 2, else 8 MiB)",
    )
    max_archive_members: int = Field(100_000, gt=0)
    max_json_body_bytes: int = Field(
        4 * 1024 * 1024,
        gt=0,
        description="largest JSON request body (413 beyond; a plan at its size bounds takes about 1.2 MB)",
    )
    allowed_hosts: list[str] = Field(
        default_factory=lambda: ["127.0.0.1", "localhost", "[::1]"],
        description="Host header values the service answers (400 otherwise; '*.example.org' patterns, '*' any); "
        "'host' is added when it names one address. Behind a reverse proxy or on the lab network: list the names "
        "clients use",
    )
    extraction_workers: int = Field(1, ge=1, le=64)
    fit_workers: int = Field(
        1,
        ge=1,
        le=64,
        description="methods fitted at once at the end of a run, each in its own process (the fits are independent: "
        "the same result); 2 on a 2-core bench PC stores the result sooner, the methods' fit events then interleave",
    )
    stream_extraction: bool = Field(
        True,
        description="measure each frame's board and rods while the bench moves to the next pose (a worker process "
        "beside the acquisition); the extraction at the end takes what it measured",
    )
    design_max_candidates: int = Field(
        1000,
        ge=20,
        le=1000,
        description="most candidate poses a plan design (POST /api/v1/plans/design) draws: its CPU time grows with "
        "them (~7 s at the default 300 on one core); a request asking for more is drawn with this many and says so",
    )
    design_max_tradeoff_designs: int = Field(
        8,
        ge=1,
        le=40,
        description="most designs one trade-off (POST /api/v1/plans/tradeoff) computes, its counts times its draws "
        "(each design ~2-7 s of CPU): a request asking for more is refused (422), naming 'counts'",
    )
    job_niceness: int = Field(
        5,
        ge=0,
        le=19,
        description="nice increment of the extraction and fit processes (the server keeps the CPU it needs to answer)",
    )
    plan_sizes: PlanSizes = PlanSizes()
    check_schedule: CheckSchedule | None = Field(
        None, description="scheduled checks of the current calibration (docs/check.md); none when absent"
    )
    config_file: Path | None = Field(None, exclude=True)

    @classmethod
    def settings_customise_sources(
        cls, settings_cls, init_settings, env_settings, dotenv_settings, file_secret_settings
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        return (init_settings, env_settings, file_secret_settings)

    @field_validator("database_url")
    @classmethod
    def _database_url(cls, v: str | None) -> str | None:
        return normalize_database_url(v)

    @property
    def db_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'i4cal.db').resolve()}"


def normalize_database_url(url: str | None) -> str | None:
    """The database URL the service uses: SQLite, or PostgreSQL through psycopg 3 (``postgresql://`` and
    ``postgres://`` are taken as ``postgresql+psycopg://``); empty means the default SQLite file.

    Raises
    ------
    ValueError
        Another database or driver (only these two are tested).
    """
    if url is None or not url.strip():
        return None
    url = url.strip()
    for prefix in ("postgres://", "postgresql://"):
        if url.startswith(prefix):
            url = "postgresql+psycopg://" + url[len(prefix) :]
    scheme = url.split("://", 1)[0] if "://" in url else ""
    if scheme not in ("sqlite", "sqlite+pysqlite", "postgresql+psycopg"):
        raise ValueError(
            f"unsupported database URL scheme {scheme or url!r}: use sqlite:///PATH or "
            "postgresql+psycopg://USER:PASSWORD@HOST:PORT/DATABASE"
        )
    return url


def load_settings(path: str | Path | None = None, **overrides: Any) -> Settings:
    """Settings from a TOML file (optional), environment variables override the file, keywords override both."""
    import os

    data: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        try:
            data = tomllib.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError("service configuration not found", file=str(p)) from None
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"not valid TOML: {exc}", file=str(p)) from None
        base = p.parent
        for key in ("data_dir", "bench_file", "camera_file"):
            if isinstance(data.get(key), str) and not Path(data[key]).is_absolute():
                data[key] = str(base / data[key])
        data["config_file"] = str(p)
    # environment wins over the file: drop file keys that the environment sets
    env_keys = {k[len("I4CAL_") :].split("__")[0].lower() for k in os.environ if k.startswith("I4CAL_")}
    data = {k: v for k, v in data.items() if k not in env_keys}
    data.update(overrides)
    from pydantic import ValidationError

    try:
        return Settings(**data)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise InputError(err["msg"], file=str(path) if path else None, field=".".join(map(str, err["loc"]))) from None
