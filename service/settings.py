"""Service settings: defaults < TOML file < environment (``OARMREG_``) < CLI flags.

One :class:`Settings` object is built in ``main`` (``oarmreg serve`` / ``demo``)
by :func:`load_settings` and passed down to :func:`service.app.create_app`;
nothing here is built at import time.

* TOML: ``configs/oarmreg.toml`` documents every key with its unit and origin.
  Relative paths in the TOML file are resolved against the file's folder.
* Environment: prefix ``OARMREG_``, ``__`` between nesting levels, e.g.
  ``OARMREG_API_TOKEN``, ``OARMREG_QUALITY__MAX_FRE_MM=0.4``,
  ``OARMREG_ROBOT__LINK_URL=simple-message://10.0.0.5:11002``.
* CLI flags are passed as ``overrides`` (dotted keys allowed: ``{"robot.link_url": ...}``).

A bad value fails at start-up with a :class:`registration.errors.ConfigError`
naming the key (``quality.max_fre_mm``) and the environment variable that
would set it.  Unsafe combinations are refused, e.g. binding a non-loopback
address without an API token.
"""

from __future__ import annotations

import contextvars
import hashlib
import ipaddress
import json
import tomllib
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from registration.errors import ConfigError
from registration.register import RegistrationParams
from registration.resources import default_phantom
from registration.stillness import DEFAULT_MAX_DEVIATION_RAD, DEFAULT_MAX_GAP_S

_REG_DEFAULTS = RegistrationParams()
"""The registration dataclass carries the defaults (one source of truth, configs/oarmreg.toml agrees)."""

DEFAULT_PHANTOM_FILE = default_phantom()
ENV_PREFIX = "OARMREG_"
MIN_TOKEN_CHARS = 16
"""Shortest accepted API token (16 chars ≈ 96 bits if random base64; OWASP: ≥ 64 bits of entropy)."""

_toml_file: contextvars.ContextVar[Path | None] = contextvars.ContextVar("oarmreg_toml_file", default=None)

_PATH_KEYS = ("watch_dir", "data_dir", "phantom_file")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Tool0FromPhantom(_Section):
    """The connecting rod: phantom frame expressed in the flange (tool0) frame."""

    translation_mm: tuple[float, float, float] = (0.0, 0.0, 200.0)
    rpy_deg: tuple[float, float, float] = (180.0, 0.0, 0.0)

    def matrix(self) -> NDArray[np.float64]:
        """4 × 4 ``tool0_from_phantom`` (mm), URDF rpy convention."""
        from registration.frames import transform_from_xyz_rpy

        return transform_from_xyz_rpy(self.translation_mm, self.rpy_deg)


class RobotSettings(_Section):
    link_url: str = "simple-message://127.0.0.1:11002"
    model: str = "tx60"
    connect_timeout_s: float = Field(default=5.0, gt=0, le=120)
    tool0_from_phantom: Tool0FromPhantom = Tool0FromPhantom()

    @field_validator("link_url")
    @classmethod
    def _scheme(cls, v: str) -> str:
        scheme = v.split("://", 1)[0] if "://" in v else ""
        if scheme not in ("simple-message", "modbus", "serial"):
            raise ValueError(
                f"expected a URL simple-message://HOST:PORT, modbus://HOST:PORT?... or "
                f"serial:///dev/...; got {v!r}"
            )
        return v

    @field_validator("model")
    @classmethod
    def _model(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("robot model must name a URDF ('tx60', 'tx2_60') or a .urdf path")
        return v


class QualitySettings(_Section):
    max_fre_mm: float = Field(default=_REG_DEFAULTS.max_fre_mm, gt=0, le=5.0)
    min_matched_spheres: int = Field(default=_REG_DEFAULTS.min_matched, ge=4, le=64)
    min_symmetry_margin: int = Field(default=_REG_DEFAULTS.min_runner_up_margin, ge=1, le=64)
    max_verification_error_mm: float = Field(default=1.0, gt=0, le=10.0)
    default_target_distance_mm: float = Field(default=150.0, ge=0, le=1000)


class StillnessSettings(_Section):
    # ≤ 100 s: the links keep 120 s of joint history (drivers.base.HISTORY_S)
    window_s: float = Field(default=60.0, gt=0, le=100)
    max_deviation_rad: float = Field(default=DEFAULT_MAX_DEVIATION_RAD, gt=0, le=0.1)
    max_gap_s: float = Field(default=DEFAULT_MAX_GAP_S, gt=0, le=60)

    @model_validator(mode="after")
    def _gap_inside_window(self) -> StillnessSettings:
        if self.max_gap_s >= self.window_s:
            raise ValueError(
                f"stillness.max_gap_s ({self.max_gap_s} s) must be shorter than stillness.window_s "
                f"({self.window_s} s), otherwise a window with no samples at all would count as still"
            )
        return self


class WatcherSettings(_Section):
    quiet_period_s: float = Field(default=2.0, gt=0, le=600)
    poll_interval_s: float = Field(default=1.0, gt=0, le=60)
    use_polling_only: bool = False


class RetentionSettings(_Section):
    """Deleting old intake scans (``service.retention``); both limits off by default."""

    max_age_days: float | None = Field(default=None, gt=0, le=36500)
    max_disk_mb: float | None = Field(default=None, gt=0)
    interval_s: float = Field(default=3600.0, ge=1, le=86400)


class DetectionSettings(_Section):
    method: Literal["default", "subvoxel", "paper"] = "default"
    use_mar: bool = True


class Settings(BaseSettings):
    """Every setting of the service (see ``configs/oarmreg.toml`` for units and origins)."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter="__",
        extra="forbid",
        frozen=True,
        validate_default=True,
    )

    watch_dir: Path = Path("oarm-export")
    data_dir: Path = Path("oarmreg-data")
    phantom_file: Path = DEFAULT_PHANTOM_FILE
    host: str = "127.0.0.1"
    port: int = Field(default=8750, ge=0, le=65535)
    api_token: SecretStr | None = None
    robot: RobotSettings = RobotSettings()
    quality: QualitySettings = QualitySettings()
    stillness: StillnessSettings = StillnessSettings()
    watcher: WatcherSettings = WatcherSettings()
    detection: DetectionSettings = DetectionSettings()
    retention: RetentionSettings = RetentionSettings()

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # First wins: CLI flags (init) > environment > TOML > defaults.
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        toml_path = _toml_file.get()
        if toml_path is not None:
            sources.append(_RelativePathsToml(settings_cls, toml_path))
        return tuple(sources)

    @field_validator("api_token")
    @classmethod
    def _token_length(cls, v: SecretStr | None) -> SecretStr | None:
        if v is None or v.get_secret_value() == "":
            return None
        if len(v.get_secret_value()) < MIN_TOKEN_CHARS:
            raise ValueError(
                f"API token is {len(v.get_secret_value())} characters; use at least {MIN_TOKEN_CHARS} "
                "random characters (e.g. python -c 'import secrets; print(secrets.token_urlsafe(24))')"
            )
        return v

    @field_validator("host")
    @classmethod
    def _host(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("bind address is empty; use 127.0.0.1 (loopback) or an interface address")
        return v.strip()

    @model_validator(mode="after")
    def _refuse_unsafe(self) -> Settings:
        if not is_loopback(self.host) and self.api_token is None:
            raise ValueError(
                f"host: binding {self.host!r} exposes the API beyond this machine; set api_token "
                f"(env {ENV_PREFIX}API_TOKEN) or bind 127.0.0.1"
            )
        if self.quality.min_symmetry_margin > self.quality.min_matched_spheres:
            raise ValueError(
                f"quality.min_symmetry_margin ({self.quality.min_symmetry_margin}) cannot exceed "
                f"quality.min_matched_spheres ({self.quality.min_matched_spheres})"
            )
        if self.watch_dir.resolve() == self.data_dir.resolve():
            raise ValueError(
                f"data_dir: must differ from watch_dir ({self.watch_dir}); the service writes its database "
                "and histograms there and would watch its own output"
            )
        return self

    # -- derived -----------------------------------------------------------------------------

    @property
    def auth_enabled(self) -> bool:
        return self.api_token is not None

    @property
    def db_path(self) -> Path:
        return self.data_dir / "oarmreg.sqlite3"

    def public_dict(self) -> dict[str, Any]:
        """JSON-ready settings without the secret (for /status and provenance)."""
        d = self.model_dump(mode="json", exclude={"api_token"})
        d["auth_enabled"] = self.auth_enabled
        return d

    def config_hash(self) -> str:
        """SHA-256 (first 16 hex) of the settings (token excluded) and the phantom file's bytes."""
        h = hashlib.sha256(
            json.dumps(self.model_dump(mode="json", exclude={"api_token"}), sort_keys=True).encode()
        )
        try:
            h.update(self.phantom_file.read_bytes())
        except OSError:
            h.update(b"<phantom file unreadable>")
        return h.hexdigest()[:16]


class _RelativePathsToml(TomlConfigSettingsSource):
    """TOML source that resolves relative paths against the TOML file's folder."""

    def __init__(self, settings_cls: type[BaseSettings], toml_file: Path) -> None:
        self._base_dir = toml_file.resolve().parent
        super().__init__(settings_cls, toml_file=toml_file)

    def __call__(self) -> dict[str, Any]:
        data = dict(super().__call__())
        for key in _PATH_KEYS:
            value = data.get(key)
            if isinstance(value, str) and value and not Path(value).expanduser().is_absolute():
                data[key] = str((self._base_dir / value).resolve())
        return data


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _nest(overrides: dict[str, Any]) -> dict[str, Any]:
    """``{"robot.link_url": u}`` → ``{"robot": {"link_url": u}}``; ``None`` values are dropped."""
    out: dict[str, Any] = {}
    for key, value in overrides.items():
        if value is None:
            continue
        parts = key.split(".")
        d = out
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = value
    return out


def _describe_error(err: Any, toml_path: Path | None) -> str:
    loc = ".".join(str(p) for p in err.get("loc", ()) if not isinstance(p, int))
    msg = str(err.get("msg", "invalid value")).removeprefix("Value error, ")
    if not loc:  # a cross-field rule: its message names the keys
        return msg + (f" (in {toml_path})" if toml_path else "")
    env = ENV_PREFIX + loc.upper().replace(".", "__")
    where = f" in {toml_path}" if toml_path else ""
    if err.get("type") == "extra_forbidden":
        return f"unknown setting '{loc}'{where}; check the spelling against configs/oarmreg.toml"
    if "input" in err and err.get("type") != "value_error":
        return f"setting '{loc}' (env {env}){where}: {msg}; got {err['input']!r}"
    return f"setting '{loc}' (env {env}){where}: {msg}"


def load_settings(config_file: str | Path | None = None, overrides: dict[str, Any] | None = None) -> Settings:
    """Build the settings: defaults < ``config_file`` (TOML) < ``OARMREG_*`` env < ``overrides``.

    Parameters
    ----------
    config_file
        TOML file; ``None`` for defaults + environment only.
    overrides
        CLI flags; dotted keys for nested settings (``"robot.link_url"``); ``None`` values ignored.

    Raises
    ------
    ConfigError
        Missing / unparsable TOML, unknown keys, bad values or unsafe combinations; the message
        names the key and the environment variable that sets it.
    """
    path = Path(config_file) if config_file is not None else None
    if path is not None:
        if not path.is_file():
            raise ConfigError(f"config file not found: {path} (pass --config FILE or unset it)")
        try:
            tomllib.loads(path.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ConfigError(f"{path}: not valid TOML: {e}") from None
    token = _toml_file.set(path)
    try:
        return Settings(**_nest(overrides or {}))
    except ValidationError as e:
        raise ConfigError("; ".join(_describe_error(err, path) for err in e.errors())) from None
    finally:
        _toml_file.reset(token)
