"""Service settings: defaults < TOML file < environment (``OARMREG_``) < CLI flags.

One :class:`Settings` object is built in ``main`` (``oarmreg serve`` / ``demo``)
by :func:`load_settings` and passed down to :func:`service.http.app.create_app`;
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
from typing import Annotated, Any, Literal, TypeVar

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

import registration.calibration.targets as _cal_targets
from registration.detection.estimators import METHODS
from registration.errors import ConfigError
from registration.io.resources import default_phantom
from registration.matching.records import (
    RegistrationParams,
)
from registration.model.stillness import DEFAULT_MAX_DEVIATION_RAD, DEFAULT_MAX_GAP_S
from service.netaddr import is_loopback

_REG_DEFAULTS = RegistrationParams()
"""The registration dataclass carries the defaults (one source of truth, configs/oarmreg.toml agrees)."""

DEFAULT_PHANTOM_FILE = default_phantom()
ENV_PREFIX = "OARMREG_"

_toml_file: contextvars.ContextVar[Path | None] = contextvars.ContextVar("oarmreg_toml_file", default=None)

_PATH_KEYS = ("watch_dir", "data_dir", "phantom_file")
_NESTED_PATH_KEYS = (
    ("tls", "cert_file"), ("tls", "key_file"),
    ("pacs", "tls_ca_file"), ("pacs", "tls_cert_file"), ("pacs", "tls_key_file"),
)  # fmt: skip


MAX_SETTING_MAGNITUDE = 1e9
"""Largest |value| of any float setting.  No setting of this service means anything beyond 1e9 of its
unit (1e9 s = 31 years, 1e9 mm = 1000 km, 1e9 MB = 1 PB); a larger value is a typo or an overflow
(``1e300`` in ``robot.tool0_from_phantom`` gave a 500 at ``/register``)."""
MAX_TRANSFORM_TRANSLATION_MM = 2000.0
"""Largest |component| of a transform setting's ``translation_mm``: the TX60's reach is 670 mm
(Stäubli TX60 data sheet); a flange-to-phantom rod or a tool centre point 2 m away is not this cell."""
MAX_TRANSFORM_RPY_DEG = 360.0
"""Largest |component| of a transform setting's ``rpy_deg``: one full turn."""

_TranslationMm = Annotated[float, Field(ge=-MAX_TRANSFORM_TRANSLATION_MM, le=MAX_TRANSFORM_TRANSLATION_MM)]
_RpyDeg = Annotated[float, Field(ge=-MAX_TRANSFORM_RPY_DEG, le=MAX_TRANSFORM_RPY_DEG)]


def _floats_of(v: Any) -> list[float]:
    if isinstance(v, float):
        return [v]
    if isinstance(v, tuple | list):
        return [x for x in v if isinstance(x, float)]
    return []


class _Section(BaseModel):
    """Every settings section: unknown keys refused; NaN / infinity refused in every float
    (``allow_inf_nan``; NaN in ``[igtl] tool0_from_tcp`` silently cut every OpenIGTLink client off),
    and every float's magnitude at most :data:`MAX_SETTING_MAGNITUDE`."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _no_absurd_float(cls, v: Any) -> Any:
        for x in _floats_of(v):
            if not abs(x) <= MAX_SETTING_MAGNITUDE:
                limit = f"{MAX_SETTING_MAGNITUDE:g}"
                raise ValueError(f"{x!r} is not a usable value (|value| must be <= {limit})")
        return v


_S = TypeVar("_S", bound=BaseModel)


def as_enabled(section: _S, error: type[ConfigError]) -> _S:
    """``section`` validated again as an enabled one, as a listener that is starting needs it (its
    allow-list rule applies to any listener, enabled in the TOML or not); a refusal raises ``error``
    with the settings' own message."""
    try:
        return type(section).model_validate({**section.model_dump(exclude_unset=True), "enabled": True})
    except ValidationError as e:
        raise error("; ".join(str(err["msg"]).removeprefix("Value error, ") for err in e.errors())) from None


def _refuse_radian_rpy(setting: str, rpy_deg: tuple[float, float, float]) -> None:
    """A degrees field holding radians (``[3.14159, 0, 0]`` for 180°) is refused: one scan cannot see
    the resulting robot-side error (registration.model.mount_checks)."""
    from registration.model.mount_checks import rpy_problems

    problems = rpy_problems(setting, rpy_deg)
    if problems:
        raise ValueError(problems[0])


class Tool0FromPhantom(_Section):
    """The connecting rod: phantom frame expressed in the flange (tool0) frame."""

    translation_mm: tuple[_TranslationMm, _TranslationMm, _TranslationMm] = (0.0, 0.0, 200.0)
    rpy_deg: tuple[_RpyDeg, _RpyDeg, _RpyDeg] = (180.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _degrees_not_radians(self) -> Tool0FromPhantom:
        _refuse_radian_rpy("robot.tool0_from_phantom", self.rpy_deg)
        return self

    def matrix(self) -> NDArray[np.float64]:
        """4 × 4 ``tool0_from_phantom`` (mm), URDF rpy convention."""
        from registration.model.frames import transform_from_xyz_rpy

        return transform_from_xyz_rpy(self.translation_mm, self.rpy_deg)


class RobotSettings(_Section):
    link_url: str = "simple-message://127.0.0.1:11002"
    model: str = "tx60"
    connect_timeout_s: float = Field(default=5.0, gt=0, le=120)
    tool0_from_phantom: Tool0FromPhantom = Tool0FromPhantom()
    # read the link in a child process (drivers/link_process.py), so DICOM decoding and
    # detection cannot starve it of the GIL; false runs it on a thread of the service (debugging)
    link_process: bool = True
    # GET /status and link_state events say "stale" only after this long without a frame (s).  The
    # link's own threshold (3 frame periods, 60 ms) flapped under ordinary load; 0.5 s is 25 frames
    # at 50 Hz, above the 0.26-0.35 s receive delays measured under decode load
    stale_after_s: float = Field(default=0.5, gt=0, le=60)

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
    """Deleting old intake scans (``service.intake.retention``); both limits off by default."""

    max_age_days: float | None = Field(default=None, gt=0, le=36500)
    max_disk_mb: float | None = Field(default=None, gt=0)
    interval_s: float = Field(default=3600.0, ge=1, le=86400)


DETECTION_METHODS: tuple[str, ...] = ("default", *METHODS)
"""``detection.method``: ``default`` (the phantom material's estimator) or a name from the estimator
table (:data:`registration.detection.estimators.METHODS`)."""


class DetectionSettings(_Section):
    # "default": the centre estimator for the phantom's sphere material
    # (registration.detection.METHOD_FOR_MATERIAL: "core" for tungsten carbide, "rays" for steel,
    # else "subvoxel").
    # Any other name: one of registration.detection.estimators.METHODS (the estimator table).
    method: str = "default"
    use_mar: bool = True

    @field_validator("method")
    @classmethod
    def _known_method(cls, v: str) -> str:
        if v not in DETECTION_METHODS:
            raise ValueError(
                f"detection.method {v!r} is not a centre estimator: use one of {', '.join(DETECTION_METHODS)}"
            )
        return v


AUTH_MODES = ("token", "none-loopback-only")
"""``api.auth``: ``token`` (default: every route but /health needs the Bearer token) or
``none-loopback-only`` (explicit opt-out; refused unless the bind address is loopback)."""


class ApiSettings(_Section):
    """HTTP hardening: authentication mode, body limit, Host / Origin allow-lists."""

    auth: Literal["token", "none-loopback-only"] = "token"
    # 1 MiB: the largest legitimate body is POST /register with 1000 targets (~60 kB of JSON);
    # 16× headroom, and far below what stalls the event loop (a 10 MB body took seconds).
    max_body_bytes: int = Field(default=1_048_576, ge=1024, le=64 * 1_048_576)
    # Host header values accepted ("name" = that name on the service's port, "name:port" exactly).
    # Empty: the bind host, localhost, 127.0.0.1 and [::1] on the service's port (DNS rebinding guard).
    allowed_hosts: tuple[str, ...] = ()
    # Origin header values accepted from browsers ("http://ui.example:8080"), besides the service's own
    # (http(s):// + the allowed hosts); a request without Origin is a non-browser client, allowed.
    allowed_origins: tuple[str, ...] = ()
    # Serve /docs (the self-hosted Swagger UI shell, public) and /openapi.json (behind the token).
    docs: bool = True
    # Lifetime of a single-use ticket from POST /events/ticket for GET /events?ticket=..., s
    # (EventSource cannot send an Authorization header; short, as it travels in the URL).
    event_ticket_ttl_s: float = Field(default=30.0, gt=0, le=600)
    # --- connection bounds (service.http.limits).  Connections held open at once; one
    # more closes the oldest idle one (no request in progress), so /health and the page keep
    # answering while a peer floods the port.  256: a browser opens at most 6 per host (Chromium's
    # per-host limit) and an SSE stream holds one, so ~40 browser tabs plus the navigation clients.
    max_connections: int = Field(default=256, ge=8, le=16384)
    # A connection must complete a request header within this long of opening (and of its previous
    # response), s; then it is closed.  uvicorn's timeout_keep_alive does not close a connection that
    # never sends a byte (idle peers stayed past 20 s).  A LAN client sends its header in
    # milliseconds; Apache's mod_reqtimeout allows 20 s for the first header bytes; 10 s frees an idle
    # peer's descriptor within seconds.
    first_request_timeout_s: float = Field(default=10.0, gt=0, le=300)
    # Connections one peer address may hold at once (capped at max_connections); one more closes that
    # address's oldest idle connection, or itself when all are busy.  64: ten browser tabs (6 each,
    # Chromium's per-host limit) plus a navigation client, while 300 slow readers from one host
    # cannot take every slot.  Behind a reverse proxy every client shares its address:
    # raise it to max_connections there.
    max_connections_per_address: int = Field(default=64, ge=1, le=16384)
    # A response whose peer reads nothing (the transport paused writing) for this long is aborted, s.
    # A LAN client drains a 1.7 MB response in well under a second; 10 s, as the header deadline,
    # frees the slot of a peer that pipelines requests and never reads (they locked HTTP out).
    write_timeout_s: float = Field(default=10.0, gt=0, le=300)
    # --- failed authentications, throttled per client address (service.http.security.AuthThrottle)
    # wrong credentials answered 401 before the address is throttled: the status page calls 7 API
    # paths when it loads with one token, so one mistyped token must not lock its user out at once
    auth_failures_before_throttle: int = Field(default=10, ge=1, le=1000)
    # the first lock-out (429 + Retry-After) after those, s; doubled on each further failure
    auth_lockout_initial_s: float = Field(default=1.0, gt=0, le=30)
    # the longest lock-out, s (at most 30 s, the longest an operator who mistyped waits)
    auth_lockout_max_s: float = Field(default=30.0, gt=0, le=30)
    # an address's failures are forgotten after this long without one, s (it ends a burst)
    auth_failure_memory_s: float = Field(default=300.0, gt=0, le=86400)
    # throttle audit rows (one per address per burst) written per minute at most; past it one
    # auth_throttle_summary row (1,000 spoofed addresses wrote 1,004 rows in 5 s)
    auth_throttle_audit_rows_per_minute: int = Field(default=20, ge=1, le=10_000)
    # proxies whose X-Forwarded-For / X-Forwarded-Proto are believed (addresses or networks, "*" =
    # any); empty: none, the client's address is the socket's (uvicorn's own default trusts 127.0.0.1)
    forwarded_allow_ips: tuple[str, ...] = ()


class DatabaseSettings(_Section):
    # How often the service checks that its database file is still the one it opened (same
    # device + inode) besides the check on every write transaction, s.
    integrity_check_interval_s: float = Field(default=5.0, gt=0, le=3600)
    # How long a write waits for another process holding the database (a backup, an sqlite3 shell)
    # before the request is answered 503 + Retry-After, s (service.store.database.BUSY_TIMEOUT_S)
    busy_timeout_s: float = Field(default=10.0, gt=0, le=60)


class Tool0FromTcp(_Section):
    """The tool centre point in the flange (tool0) frame, for OpenIGTLink ``ToolToImage``."""

    translation_mm: tuple[_TranslationMm, _TranslationMm, _TranslationMm] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[_RpyDeg, _RpyDeg, _RpyDeg] = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _degrees_not_radians(self) -> Tool0FromTcp:
        _refuse_radian_rpy("igtl.tool0_from_tcp", self.rpy_deg)
        return self

    def matrix(self) -> NDArray[np.float64]:
        """4 × 4 ``tool0_from_tcp`` (mm), URDF rpy convention (identity by default)."""
        from registration.model.frames import transform_from_xyz_rpy

        return transform_from_xyz_rpy(self.translation_mm, self.rpy_deg)


def _check_networks(values: tuple[str, ...]) -> tuple[str, ...]:
    for v in values:
        try:
            ipaddress.ip_network(v, strict=False)
        except ValueError as e:
            raise ValueError(f"{v!r} is not an IP address or network (CIDR): {e}") from None
    return values


class DicomSettings(_Section):
    """DICOM Storage SCP (C-STORE from the O-arm), :mod:`service.intake.storage_scp`."""

    enabled: bool = False
    host: str = "127.0.0.1"
    ae_title: str = Field(default="OARMREG", min_length=1, max_length=16)
    port: int = Field(default=11112, ge=0, le=65535)
    allowed_calling_ae_titles: tuple[str, ...] = ()
    allowed_peer_addresses: tuple[str, ...] = ()
    # --- bounds (service.intake.storage_scp.StorageScp reads them from here)
    # association negotiation / release, s (pynetdicom's ARTIM timer; its default 30 s let 30 silent
    # sockets hold every slot for ~30 s)
    acse_timeout_s: float = Field(default=10.0, gt=0, le=3600)
    # between DIMSE messages of an association, s (pynetdicom's default)
    dimse_timeout_s: float = Field(default=30.0, gt=0, le=3600)
    # an association without any traffic is aborted after this, s (pynetdicom's default)
    network_timeout_s: float = Field(default=60.0, gt=0, le=3600)
    # per connection: a read or write without progress for this long drops the peer, s (a half-sent
    # A-ASSOCIATE-RQ otherwise held its thread and slot with all three timeouts at 3 s)
    socket_timeout_s: float = Field(default=10.0, gt=0, le=3600)
    # concurrent associations (pynetdicom's default 10)
    maximum_associations: int = Field(default=10, ge=1, le=1000)
    # of those, held at once by one peer address (A-ASSOCIATE-RJ transient beyond it), so one host
    # cannot lock the O-arm out (ten echoing associations did); an O-arm sends one at a time
    max_associations_per_peer: int = Field(default=5, ge=1, le=1000)
    # largest C-STORE instance, MB (a 512 x 512 x 192 Enhanced CT is ~100 MB; received to a temp file)
    max_instance_mb: float = Field(default=1024.0, gt=0, le=65536)

    @field_validator("allowed_peer_addresses")
    @classmethod
    def _networks(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        return _check_networks(v)

    @field_validator("allowed_calling_ae_titles")
    @classmethod
    def _callers(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        """``TITLE`` or ``TITLE@ADDRESS[/PREFIX]``: the address part must parse."""
        _check_networks(tuple(e.partition("@")[2].strip() for e in v if "@" in e))
        return v

    @field_validator("ae_title")
    @classmethod
    def _ae_title(cls, v: str) -> str:
        if not (v.isascii() and v.strip()):
            raise ValueError(f"dicom.ae_title must be 1–16 ASCII characters, not all spaces, got {v!r}")
        return v

    @model_validator(mode="after")
    def _allow_lists(self) -> DicomSettings:
        if (
            self.enabled
            and not is_loopback(self.host)
            and not (self.allowed_calling_ae_titles or self.allowed_peer_addresses)
        ):
            raise ValueError(
                f"dicom.host: accepting DICOM on {self.host!r} with both allow-lists empty would let anyone "
                "on the network store images; set dicom.allowed_calling_ae_titles (the O-arm's AE title) "
                "and/or dicom.allowed_peer_addresses, or bind 127.0.0.1"
            )
        return self


IGTL_BODY_LIMIT_MAX_BYTES = 1024 * 1024
"""No OpenIGTLink per-type body limit may exceed 1 MiB: its CRC (crcmod's C code, ~290 MB/s) stays
under ~4 ms."""


class IgtlSettings(_Section):
    """OpenIGTLink server (``RobotToImage``, ``ToolToImage``), :mod:`service.navigation.igtl.server`."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(default=18944, ge=0, le=65535)
    allowed_peer_addresses: tuple[str, ...] = ()
    period_s: float = Field(default=1.0, gt=0, le=60)
    tool0_from_tcp: Tool0FromTcp = Tool0FromTcp()
    # Listener limits (docs/security.md, "OpenIGTLink listener limits").
    max_clients: int = Field(default=32, ge=1, le=1024)
    """Connections held at once; more are closed at once and counted (``refused_full``).  Navigation
    workstations on one OR network: a Slicer or two, a PLUS, a recorder; 32 is ample, and bounds the
    descriptors the listener can hold (:func:`descriptor_budget` sums the listeners' maxima against
    RLIMIT_NOFILE)."""
    max_clients_per_address: int = Field(default=8, ge=1, le=1024)
    """Connections one peer address may hold (at most ``max_clients``: the default is capped at it, a
    larger value set explicitly is refused); one more from that address is closed at once and counted
    (``refused_per_address``), so one host's idle sockets cannot lock another host's navigation out.
    8: a workstation runs a Slicer, a PLUS and a recorder, a connection or two each, with room."""
    max_query_answers_per_s: float = Field(default=240.0, gt=0, le=10_000)
    """Queries (``GET_``) answered per client per second; a client that asks faster is read no faster
    (its queries wait in its own socket) and gets the latest state, not a backlog.  Navigation polls at
    most at 60 Hz (a display's refresh): 60 Hz x 4 queries (the two TRANSFORMs, the POINT list,
    GET_STATUS)."""
    status_max_body_bytes: int = Field(default=4096, ge=64, le=IGTL_BODY_LIMIT_MAX_BYTES)
    """Largest STATUS body a client may send, bytes; a larger BODY_SIZE closes its connection unread.
    A STATUS is 30 bytes + its status string (+ 12 + metadata in version 2); SlicerOpenIGTLink's
    version-2 announcement is 44 bytes; 4 KiB leaves room for a PLUS-style error text."""
    query_max_body_bytes: int = Field(default=1024, ge=64, le=IGTL_BODY_LIMIT_MAX_BYTES)
    """Largest GET_/STT_/STP_/RTS_ body, bytes: no content in version 1, 12 + a few metadata pairs in
    version 2."""
    other_max_body_bytes: int = Field(default=64 * 1024, ge=64, le=IGTL_BODY_LIMIT_MAX_BYTES)
    """Largest body of any other type (read and ignored), bytes: TRANSFORM 48 B, POINT 136 B a point,
    a STRING at most 64 KiB (uint16 length) — not images."""
    stall_timeout_s: float = Field(default=5.0, gt=0, le=300)
    """A message begun must be complete within this, s; else its connection is closed (58 B + at most
    64 KiB on loopback or a LAN takes milliseconds; 5 s forgives a congested link, frees a slot soon)."""
    # Per-client delivery.
    poll_period_s: float = Field(default=0.01, gt=0, le=1)
    """How often new joint samples are looked for, s: 100 Hz, twice the 50 Hz VAL3 rate."""
    joint_max_age_s: float = Field(default=0.25, gt=0, le=60)
    """A joint sample older than this makes ToolToImage INVALID, s (12 samples at the 50 Hz VAL3 rate):
    its one freshness limit, named in the ``Reason`` (the driver's own three-frame "stale" does not
    apply; service/navigation/igtl/publisher.py)."""
    client_queue_max: int = Field(default=64, ge=1, le=4096)
    """Messages queued per client; when full the oldest is dropped."""
    client_buffer_bytes: int = Field(default=64 * 1024, ge=1024, le=64 * 1024 * 1024)
    """Transport write-buffer high-water mark per client, bytes; a client that sends a query while more
    than this is waiting for it to read (its socket buffer full as well) is dropped at once
    (``slow_reader_drops``): it asks faster than it reads."""
    socket_send_buffer_bytes: int = Field(default=64 * 1024, ge=1024, le=64 * 1024 * 1024)
    """SO_SNDBUF of each accepted socket, bytes: bounds what a stalled client can pile up in the kernel
    (and so how fast it is detected) instead of Linux's autotuning up to 4 MiB."""
    slow_client_timeout_s: float = Field(default=2.0, gt=0, le=300)
    """A client whose socket accepts nothing for this long is disconnected, s."""
    send_invalid_transforms_v2: bool = False
    """Send an INVALID device's TRANSFORM (identity, ``TransformStatus=INVALID``) to header-version-2
    clients besides its STATUS; version-1 clients never get one (PLUS: SendValidTransformsOnly)."""

    @field_validator("allowed_peer_addresses")
    @classmethod
    def _networks(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        return _check_networks(v)

    @model_validator(mode="after")
    def _share_within_max(self) -> IgtlSettings:
        share, most = self.max_clients_per_address, self.max_clients
        if "max_clients_per_address" in self.model_fields_set and share > most:
            raise ValueError(
                f"igtl.max_clients_per_address ({share}) is more than igtl.max_clients ({most}): one "
                "address's share must fit in the listener"
            )
        return self

    @property
    def address_share(self) -> int:
        """Connections one peer address may hold: ``max_clients_per_address`` capped at ``max_clients``."""
        return min(self.max_clients_per_address, self.max_clients)

    @model_validator(mode="after")
    def _allow_list(self) -> IgtlSettings:
        if self.enabled and not is_loopback(self.host) and not self.allowed_peer_addresses:
            raise ValueError(
                f"igtl.host: serving OpenIGTLink on {self.host!r} needs igtl.allowed_peer_addresses (the "
                "protocol has no authentication), e.g. ['10.0.0.12'], or bind 127.0.0.1"
            )
        return self


class TlsSettings(_Section):
    """HTTPS for the REST API (uvicorn's ``ssl_certfile`` / ``ssl_keyfile``)."""

    cert_file: Path | None = None
    key_file: Path | None = None
    allow_insecure_http: bool = False
    """Permit plain HTTP on a non-loopback bind (a TLS-terminating proxy in front, say)."""

    @field_validator("cert_file", "key_file", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v

    @model_validator(mode="after")
    def _pair(self) -> TlsSettings:
        if (self.cert_file is None) != (self.key_file is None):
            raise ValueError("tls.cert_file and tls.key_file must be set together (PEM certificate + key)")
        for key, path in (("tls.cert_file", self.cert_file), ("tls.key_file", self.key_file)):
            if path is not None and not path.is_file():
                raise ValueError(f"{key}: {path} is not a readable file")
        return self

    @property
    def enabled(self) -> bool:
        return self.cert_file is not None


class LogSettings(_Section):
    """``oarmreg serve`` logging; ``-v`` / ``--log-level`` / ``--log-format`` override it."""

    # INFO: the start-up line (every listener, the data folder), scans, registrations, refusals.
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    # "json": one JSON object per line (ts, level, logger, message, exc) for journald / log shippers.
    format: Literal["text", "json"] = "text"


class PacsSettings(_Section):
    """Archive each accepted registration's Spatial Registration object to a PACS by C-STORE
    (:mod:`service.navigation.pacs`).  Off while ``host`` is empty."""

    host: str = ""
    port: int = Field(default=104, ge=1, le=65535)
    ae_title: str = Field(default="", max_length=16)
    """The PACS's (called) AE title."""
    calling_ae_title: str = Field(default="OARMREG", min_length=1, max_length=16)
    """Ours, as the PACS must know it."""
    timeout_s: float = Field(default=30.0, gt=0, le=600)
    """Association, DIMSE and network timeout of one attempt."""
    retry_initial_s: float = Field(default=5.0, gt=0, le=3600)
    """Wait before the first retry after a link failure; doubled per failure up to retry_max_s."""
    retry_max_s: float = Field(default=300.0, gt=0, le=86400)
    give_up_after_s: float = Field(default=7 * 86400.0, gt=0)
    """A send still failing on the link this long after it was queued becomes ``failed``."""
    tls_ca_file: Path | None = None
    """PEM CA bundle of the PACS's certificate: set → the association uses TLS (DICOM PS3.15 B.1)."""
    tls_cert_file: Path | None = None
    tls_key_file: Path | None = None
    """Our client certificate and key (PEM), when the PACS asks for one."""

    @field_validator("tls_ca_file", "tls_cert_file", "tls_key_file", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v

    @model_validator(mode="after")
    def _complete(self) -> PacsSettings:
        if self.host and not self.ae_title:
            raise ValueError("pacs.ae_title: the PACS's AE title is required when pacs.host is set")
        if (self.tls_cert_file is None) != (self.tls_key_file is None):
            raise ValueError("pacs.tls_cert_file and pacs.tls_key_file must be set together")
        if self.tls_cert_file is not None and self.tls_ca_file is None:
            raise ValueError("pacs.tls_cert_file needs pacs.tls_ca_file (TLS is on only with a CA)")
        for key in ("tls_ca_file", "tls_cert_file", "tls_key_file"):
            path = getattr(self, key)
            if path is not None and not path.is_file():
                raise ValueError(f"pacs.{key}: {path} is not a readable file")
        return self

    @property
    def enabled(self) -> bool:
        return bool(self.host)


class ServiceSection(_Section):
    auto_register: bool = False
    """Register every scan as soon as it is recorded complete (and push the result)."""


class HealthSettings(_Section):
    """When ``GET /status`` (and ``GET /ready``) turn unhealthy (service.http.health, docs/safety.md)."""

    # the robot link down or stale this long (s) is a problem.  Longer than one reconnect (back-off
    # capped at 0.5 s plus a connect, docs/robot-link.md), so a controller that blips is not a problem;
    # far shorter than an O-arm spin (~13-25 s), so a dead link shows before the scan is taken
    link_hold_off_s: float = Field(default=3.0, gt=0, le=600)


class QaSettings(_Section):
    """The QA drift rule (:mod:`service.registrations.qa_drift`, docs/operations.md "QA drift")."""

    # the last N QA checks (verifications at a QA protocol's pose) under the active calibration the
    # rule looks at.  3: one protocol run of three poses, or three weekly runs of one; fewer than N
    # checks never fire (one bad pose is the verification gate's business, not a drift)
    drift_window: int = Field(default=3, ge=2, le=100)
    # mm; their mean above this fires.  0.5 mm: half the verification gate's default pass limit
    # (quality.max_verification_error_mm, 1.0 mm) and the calibration's own acceptance limit on its
    # predicted error (max_predicted_error_mm, 0.5 mm, docs/calibration.md): a cell whose QA means
    # exceed what its calibration predicts no longer behaves as calibrated, long before checks fail
    drift_mean_mm: float = Field(default=0.5, gt=0, le=10.0)
    # mm; the N means rising at every check and by more than this from first to last fires too.
    # 0.2 mm: 40 % of drift_mean_mm, so a steady rise is caught before the limit; an engineering
    # choice, not measured on a cell (revisit with the site's QA history)
    drift_rise_mm: float = Field(default=0.2, gt=0, le=10.0)


class CalibrationSettings(_Section):
    """The calibration pose planner (``oarmreg calibrate plan``, ``demo --calibrate``;
    docs/calibration.md "Pose planner")."""

    # mm; the planner adds poses until its predicted RMS sphere error over the working volume (what
    # held-out poses measure) is at most this.  0.075 mm: 1.5 × the floor (true geometric model,
    # oracle registration) of an unseen simulated TX60 cell, where 20 planned poses reached 0.072 mm
    # and 10 gave 0.106 mm (registration/calibration/targets.py)
    target_rms_mm: float = Field(default=_cal_targets.TARGET_RMS_MM, gt=0, le=5.0)
    # the most poses the planner proposes on its own (each is one O-arm spin of the phantom, no
    # patient); --n forces a count
    max_poses: int = Field(default=_cal_targets.MAX_PLANNED_POSES, ge=10, le=200)


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
    # A read-only token for wall displays: sees everything, changes nothing (every POST
    # but /events/ticket answers 403).  Unset: none.  Same strength rule as api_token, and different.
    api_readonly_token: SecretStr | None = None
    robot: RobotSettings = RobotSettings()
    quality: QualitySettings = QualitySettings()
    stillness: StillnessSettings = StillnessSettings()
    watcher: WatcherSettings = WatcherSettings()
    detection: DetectionSettings = DetectionSettings()
    api: ApiSettings = ApiSettings()
    database: DatabaseSettings = DatabaseSettings()
    dicom: DicomSettings = DicomSettings()
    igtl: IgtlSettings = IgtlSettings()
    tls: TlsSettings = TlsSettings()
    service: ServiceSection = ServiceSection()
    retention: RetentionSettings = RetentionSettings()
    health: HealthSettings = HealthSettings()
    log: LogSettings = LogSettings()

    pacs: PacsSettings = PacsSettings()
    qa: QaSettings = QaSettings()
    calibration: CalibrationSettings = CalibrationSettings()

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

    @field_validator("api_token", "api_readonly_token")
    @classmethod
    def _token_strength(cls, v: SecretStr | None) -> SecretStr | None:
        """Refuse a token that can be guessed (:func:`service.token_strength.token_problem`)."""
        from service.token_strength import token_problem

        if v is None or v.get_secret_value() == "":
            return None
        problem = token_problem(v.get_secret_value())
        if problem is not None:
            raise ValueError(f"the API token can be guessed: {problem}")
        return v

    @field_validator("host")
    @classmethod
    def _host(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("bind address is empty; use 127.0.0.1 (loopback) or an interface address")
        return v.strip()

    @model_validator(mode="after")
    def _refuse_unsafe(self) -> Settings:
        if self.api.auth == "none-loopback-only" and not is_loopback(self.host):
            raise ValueError(
                f"api.auth: 'none-loopback-only' cannot be used with host {self.host!r}; bind 127.0.0.1 "
                "or use api.auth = 'token' with api_token"
            )
        if self.api.auth == "none-loopback-only" and self.api_token is not None:
            raise ValueError(
                "api.auth is 'none-loopback-only' but api_token is set; choose one: api.auth = 'token' "
                f"(env {ENV_PREFIX}API__AUTH) or an empty api_token"
            )
        if not is_loopback(self.host) and self.api_token is None:
            raise ValueError(
                f"host: binding {self.host!r} exposes the API beyond this machine; set api_token "
                f"(env {ENV_PREFIX}API_TOKEN) or bind 127.0.0.1"
            )
        if not is_loopback(self.host) and not self.tls.enabled and not self.tls.allow_insecure_http:
            raise ValueError(
                f"host: binding {self.host!r} would send the API token in clear text; set tls.cert_file and "
                "tls.key_file (or --tls-cert / --tls-key), or tls.allow_insecure_http = true behind a "
                "TLS-terminating proxy"
            )
        if self.api_readonly_token is not None and (
            self.api_token is None
            or self.api_readonly_token.get_secret_value() == self.api_token.get_secret_value()
        ):
            raise ValueError(
                "api_readonly_token needs api_token set and must differ from it (otherwise a wall "
                f"display could change the registration); env {ENV_PREFIX}API_READONLY_TOKEN"
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
        return self.api_token is not None and self.api.auth == "token"

    def check_serving(self) -> None:
        """Refuse to serve with no way to authenticate (``api.auth = 'token'`` without ``api_token``).

        Raises
        ------
        ConfigError
            Names both ways out: a token, or the explicit loopback-only no-auth mode.
        """
        if self.api.auth == "token" and self.api_token is None:
            raise ConfigError(
                f"api_token is not set and api.auth is 'token' (the default): set {ENV_PREFIX}API_TOKEN "
                "to a random token (make one with `oarmreg token`), "
                "or, on a loopback bind only, api.auth = 'none-loopback-only' to serve without authentication"
            )

    def check_robot_side(self, phantom_size_mm: NDArray[np.float64]) -> None:
        """Refuse a rod whose length cannot be right for this phantom and arm (metres typed in the
        millimetre field, a rod beyond the arm's reach; registration.model.mount_checks).

        Raises
        ------
        ConfigError
            Naming ``robot.tool0_from_phantom`` and the likely unit.
        """
        from registration.model.mount_checks import rod_length_problems

        rod = self.robot.tool0_from_phantom
        half = float(np.min(np.asarray(phantom_size_mm, dtype=np.float64))) / 2.0
        problems = rod_length_problems("robot.tool0_from_phantom", rod.translation_mm, half)
        if problems:
            raise ConfigError(problems[0])

    @property
    def db_path(self) -> Path:
        return self.data_dir / "oarmreg.sqlite3"

    def public_dict(self) -> dict[str, Any]:
        """JSON-ready settings without the secret (for /status and provenance)."""
        d = self.model_dump(mode="json", exclude={"api_token", "api_readonly_token"})
        d["auth_enabled"] = self.auth_enabled
        return d

    def config_hash(self) -> str:
        """SHA-256 (first 16 hex) of the settings (token excluded) and the phantom file's bytes."""
        h = hashlib.sha256(
            json.dumps(
                self.model_dump(mode="json", exclude={"api_token", "api_readonly_token"}), sort_keys=True
            ).encode()
        )
        from registration.dicom.errors import NotRegularFileError
        from registration.dicom.files import open_regular

        try:
            with open_regular(self.phantom_file) as f:  # never blocks on a FIFO or reads a device
                h.update(f.read())
        except (OSError, NotRegularFileError):
            h.update(b"<phantom file unreadable>")
        return h.hexdigest()[:16]


DESCRIPTOR_MARGIN = 256
"""Descriptors besides the listeners' peers: the database and its journal, the robot link (a socket
and, with ``robot.link_process``, its child's pipes), the listening sockets, the folder watcher's
inotify, scan and temp files being read or written, logs, the interpreter's own.  An idle service
with every listener on holds 26 (``ls /proc/PID/fd``, benchmarks/bench_hostile.py); a registration
decoding a series adds a few more."""


def descriptor_budget(settings: Settings) -> list[tuple[str, int]]:
    """``(setting, descriptors)`` the configured maxima can hold open at once: one per
    HTTP connection, OpenIGTLink client and DICOM association, plus :data:`DESCRIPTOR_MARGIN`."""
    out = [("api.max_connections", settings.api.max_connections)]
    if settings.igtl.enabled:
        out.append(("igtl.max_clients", settings.igtl.max_clients))
    if settings.dicom.enabled:
        # one socket per association, plus the temp file of the instance being received
        out.append(("dicom.maximum_associations", 2 * settings.dicom.maximum_associations))
    out.append(("margin (files, database, robot link)", DESCRIPTOR_MARGIN))
    return out


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
        for section, key in _NESTED_PATH_KEYS:
            sub = data.get(section)
            value = sub.get(key) if isinstance(sub, dict) else None
            if isinstance(value, str) and value and not Path(value).expanduser().is_absolute():
                assert isinstance(sub, dict)
                data[section] = {**sub, key: str((self._base_dir / value).resolve())}
        return data


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


def _toml_has(toml_data: dict[str, Any] | None, loc: str) -> bool:
    """Whether the dotted key ``loc`` is written in the TOML file's data."""
    node: Any = toml_data or {}
    for part in loc.split("."):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def _close_key(loc: str) -> str:
    """``; did you mean 'dicom.port'?`` for a misspelt dotted key, else ``""``."""
    import difflib

    close = difflib.get_close_matches(loc, sorted(_setting_keys()), n=1, cutoff=0.75)
    return f"; did you mean '{close[0]}'?" if close else ""


def _describe_error(err: Any, toml_path: Path | None, toml_data: dict[str, Any] | None = None) -> str:
    """One problem of a ``ValidationError``, naming the key and where its value came from: the
    environment variable if it is set, else the TOML file that holds the key."""
    import os

    loc = ".".join(str(p) for p in err.get("loc", ()) if not isinstance(p, int))
    msg = str(err.get("msg", "invalid value")).removeprefix("Value error, ")
    if not loc:  # a cross-field rule: its message names the keys
        return msg + (f" (in {toml_path})" if toml_path else "")
    env = ENV_PREFIX + loc.upper().replace(".", "__")
    where = f" in {toml_path}" if toml_path else ""
    if err.get("type") == "extra_forbidden":
        look = f"fix it in {toml_path}" if toml_path else "fix its name"
        return (
            f"unknown setting '{loc}'{where}{_close_key(loc)}; {look} "
            "(`oarmreg config check` lists every setting)"
        )
    if env in os.environ:
        source = f"from the environment variable {env}"
    elif toml_path is not None and _toml_has(toml_data, loc):
        source = f"in {toml_path}"
    else:
        source = f"(set it in the TOML file or with {env})"
    got = f"; got {err['input']!r}" if "input" in err and err.get("type") != "value_error" else ""
    return f"setting '{loc}' {source}: {msg}{got}"


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
    toml_data: dict[str, Any] | None = None
    if path is not None:
        if not path.is_file():
            raise ConfigError(f"config file not found: {path} (pass --config FILE or unset it)")
        try:
            toml_data = tomllib.loads(path.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ConfigError(f"{path}: not valid TOML: {e}") from None
    env_problems, env_keys = _unknown_environment()
    token = _toml_file.set(path)
    try:
        settings = Settings(**_nest(overrides or {}))
    except ValidationError as e:
        problems = [
            _describe_error(err, path, toml_data)
            for err in e.errors()
            if not (err.get("type") == "extra_forbidden" and _loc(err) in env_keys)
        ]
        raise ConfigError("; ".join(env_problems + problems)) from None
    finally:
        _toml_file.reset(token)
    if env_problems:
        raise ConfigError("; ".join(env_problems))
    return settings


NON_SETTING_ENV_VARS = frozenset({"OARMREG_CHROMIUM", "OARMREG_FAULT_KILLS"})
"""``OARMREG_*`` variables that are not settings: the test suite's own (tests/browser/harness.py,
tests/faults/test_fault_kill.py)."""


def _loc(err: Any) -> str:
    return ".".join(str(p) for p in err.get("loc", ()) if not isinstance(p, int))


def _setting_keys(model: type[BaseModel] = Settings, prefix: str = "") -> set[str]:
    """Every dotted setting key (``quality.max_fre_mm``) and section (``quality``) of ``model``."""
    keys: set[str] = set()
    for name, field in model.model_fields.items():
        key = prefix + name
        keys.add(key)
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            keys |= _setting_keys(ann, key + ".")
    return keys


def _unknown_environment(environ: dict[str, str] | None = None) -> tuple[list[str], set[str]]:
    """Problems with ``OARMREG_*`` environment variables that name no setting (a typo such as
    ``OARMREG_API_TOKN`` would otherwise leave the token unset without a word), and their dotted
    keys (so the model's own "unknown setting" for a nested one is not blamed on the TOML file)."""
    import difflib
    import os

    env = os.environ if environ is None else environ
    known = _setting_keys()
    names = {ENV_PREFIX + k.upper().replace(".", "__"): k for k in known}
    problems: list[str] = []
    keys: set[str] = set()
    for var in sorted(env):
        upper = var.upper()
        if not upper.startswith(ENV_PREFIX) or upper in NON_SETTING_ENV_VARS or upper in names:
            continue
        keys.add(upper.removeprefix(ENV_PREFIX).lower().replace("__", "."))
        close = difflib.get_close_matches(upper, names, n=1, cutoff=0.8)
        hint = f"did you mean {close[0]}? " if close else ""
        problems.append(
            f"unknown environment variable {var} (no setting "
            f"'{upper.removeprefix(ENV_PREFIX).lower().replace('__', '.')}'); {hint}fix its name or unset it "
            "(OARMREG_ + key in capitals, '__' between section and key; `oarmreg config check` lists keys)"
        )
    return problems, keys
