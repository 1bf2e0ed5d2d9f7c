"""service/settings.py: precedence, one test per validation rule, unsafe combinations."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from registration.errors import ConfigError
from service.settings import Settings, is_loopback, load_settings
from tests.helpers.tokens import make_token

REPO = Path(__file__).resolve().parents[3]
TOKEN = make_token()


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    for k in list(os.environ):
        if k.startswith("OARMREG_"):
            monkeypatch.delenv(k)


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cfg.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_defaults_are_valid_and_loopback() -> None:
    s = load_settings()
    assert s.host == "127.0.0.1" and s.api_token is None and not s.auth_enabled
    assert s.robot.tool0_from_phantom.translation_mm == (0.0, 0.0, 200.0)
    assert np.allclose(
        s.robot.tool0_from_phantom.matrix()[:3, 2], [0, 0, -1]
    )  # phantom +z back at the flange
    assert np.allclose(s.robot.tool0_from_phantom.matrix()[:3, 3], [0, 0, 200])


def test_shipped_config_loads_and_resolves_paths_against_its_folder() -> None:
    from registration.io.resources import default_phantom

    s = load_settings(REPO / "configs" / "oarmreg.toml")
    # no phantom_file in the shipped TOML: the packaged cube, wherever the TOML is copied (issue 34)
    assert s.phantom_file == default_phantom()
    assert s.phantom_file.is_file()
    assert s.watch_dir == REPO / "oarm-export"


def test_precedence_defaults_toml_env_cli(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = write(
        tmp_path,
        'port = 9001\n[quality]\nmax_fre_mm = 0.4\nmin_matched_spheres = 8\n[robot]\nmodel = "tx2_60"\n',
    )
    s = load_settings(cfg)
    assert (s.port, s.quality.max_fre_mm, s.quality.min_matched_spheres, s.robot.model) == (
        9001,
        0.4,
        8,
        "tx2_60",
    )
    monkeypatch.setenv("OARMREG_PORT", "9002")
    monkeypatch.setenv("OARMREG_QUALITY__MAX_FRE_MM", "0.3")
    s = load_settings(cfg)
    assert (s.port, s.quality.max_fre_mm, s.quality.min_matched_spheres) == (
        9002,
        0.3,
        8,
    )  # nested merge kept 8
    s = load_settings(cfg, {"port": 9003, "robot.link_url": "modbus://10.0.0.2:502", "host": None})
    assert s.port == 9003 and s.robot.link_url == "modbus://10.0.0.2:502" and s.robot.model == "tx2_60"


def test_env_api_token(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OARMREG_API_TOKEN", TOKEN)
    s = load_settings()
    assert s.auth_enabled and s.api_token is not None and s.api_token.get_secret_value() == TOKEN
    assert TOKEN not in repr(s) and "api_token" not in s.public_dict()


def test_bad_value_names_key_and_its_source(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bad value in the file names the file and the key (not an environment variable that is not
    set); a bad value from the environment names the variable (issue 42, item 4)."""
    monkeypatch.delenv("OARMREG_DICOM__PORT", raising=False)
    toml = write(tmp_path, "[dicom]\nport = 99999\n")
    with pytest.raises(ConfigError) as info:
        load_settings(toml)
    assert f"setting 'dicom.port' in {toml}" in str(info.value)
    assert "OARMREG_DICOM__PORT" not in str(info.value)
    monkeypatch.setenv("OARMREG_QUALITY__MAX_FRE_MM", "-1")
    with pytest.raises(
        ConfigError, match=r"quality\.max_fre_mm' from the environment variable OARMREG_QUALITY__MAX_FRE_MM"
    ):
        load_settings(None)


def test_a_typo_points_to_the_file_read_and_the_nearest_key(tmp_path: Path) -> None:
    toml = write(tmp_path, "[dicom]\nprot = 11112\n")
    with pytest.raises(ConfigError) as info:
        load_settings(toml)
    text = str(info.value)
    assert "did you mean 'dicom.port'?" in text and f"fix it in {toml}" in text
    assert "configs/oarmreg.toml" not in text


def test_unknown_key_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"unknown setting 'quality\.max_fre'"):
        load_settings(write(tmp_path, "[quality]\nmax_fre = 0.5\n"))


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="config file not found"):
        load_settings(tmp_path / "nope.toml")


def test_invalid_toml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_settings(write(tmp_path, "port = = 3\n"))


def test_non_loopback_without_token_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"host.*api_token"):
        load_settings(None, {"host": "0.0.0.0"})
    insecure_ok = {"host": "0.0.0.0", "api_token": TOKEN, "tls.allow_insecure_http": True}
    assert load_settings(None, insecure_ok).host == "0.0.0.0"


def test_short_token_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"api_token.*at least 22 characters.*oarmreg token"):
        load_settings(None, {"api_token": "short"})


def test_empty_token_disables_auth_on_loopback() -> None:
    assert load_settings(None, {"api_token": ""}).api_token is None


def test_bad_link_url_scheme() -> None:
    with pytest.raises(ConfigError, match=r"robot\.link_url"):
        load_settings(None, {"robot.link_url": "http://robot:80"})


def test_stillness_gap_must_be_shorter_than_window() -> None:
    with pytest.raises(ConfigError, match="max_gap_s"):
        load_settings(None, {"stillness.window_s": 0.5, "stillness.max_gap_s": 0.5})


def test_symmetry_margin_cannot_exceed_min_matched() -> None:
    with pytest.raises(ConfigError, match="min_symmetry_margin"):
        load_settings(None, {"quality.min_matched_spheres": 6, "quality.min_symmetry_margin": 7})


def test_watch_and_data_must_differ(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="data_dir"):
        load_settings(None, {"watch_dir": tmp_path, "data_dir": tmp_path})


def test_tool0_from_phantom_needs_three_values() -> None:
    with pytest.raises(ConfigError, match=r"robot\.tool0_from_phantom\.translation_mm"):
        load_settings(None, {"robot.tool0_from_phantom.translation_mm": [0, 0]})


def test_config_hash_ignores_token_and_tracks_values() -> None:
    a = load_settings()
    b = load_settings(None, {"api_token": TOKEN})
    c = load_settings(None, {"quality.max_fre_mm": 0.3})
    assert a.config_hash() == b.config_hash() != c.config_hash()


def test_no_settings_at_import_time() -> None:
    import service.settings as mod

    assert not any(isinstance(v, Settings) for v in vars(mod).values())


@pytest.mark.parametrize(
    ("host", "loop"),
    [
        ("127.0.0.1", True),
        ("::1", True),
        ("localhost", True),
        ("0.0.0.0", False),
        ("10.1.2.3", False),
        ("robot.lan", False),
    ],
)
def test_is_loopback(host: str, loop: bool) -> None:
    assert is_loopback(host) is loop


def test_an_unknown_environment_variable_is_named_as_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 34: OARMREG_API_TOKN was ignored without a word (auth silently off); a nested typo
    was blamed on the TOML file."""
    monkeypatch.setenv("OARMREG_API_TOKN", TOKEN)
    with pytest.raises(
        ConfigError, match=r"environment variable OARMREG_API_TOKN .*did you mean OARMREG_API_TOKEN"
    ):
        load_settings()
    monkeypatch.delenv("OARMREG_API_TOKN")
    monkeypatch.setenv("OARMREG_QUALITY__MAX_FRE", "0.4")
    cfg = write(tmp_path, "port = 9001\n")
    with pytest.raises(ConfigError) as e:
        load_settings(cfg)
    assert "environment variable OARMREG_QUALITY__MAX_FRE" in str(e.value)
    assert str(cfg) not in str(e.value) and "OARMREG_QUALITY__MAX_FRE_MM" in str(e.value)
    monkeypatch.setenv("OARMREG_CHROMIUM", "/usr/bin/chromium")  # the test suite's own: not a setting
    monkeypatch.delenv("OARMREG_QUALITY__MAX_FRE")
    assert load_settings(cfg).port == 9001
