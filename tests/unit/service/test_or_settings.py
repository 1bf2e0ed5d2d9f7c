"""Settings of the operating-room interfaces: [dicom], [igtl], [tls], [service] (issue #12)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from registration.errors import ConfigError
from service.settings import load_settings
from tests.helpers.tokens import make_token

TOKEN = make_token()


def test_defaults_are_loopback_and_off() -> None:
    s = load_settings(None)
    assert (s.dicom.enabled, s.dicom.host, s.dicom.ae_title, s.dicom.port) == (
        False,
        "127.0.0.1",
        "OARMREG",
        11112,
    )
    assert (s.igtl.enabled, s.igtl.host, s.igtl.port) == (False, "127.0.0.1", 18944)
    assert not s.tls.enabled and not s.service.auto_register
    np.testing.assert_array_equal(s.igtl.tool0_from_tcp.matrix(), np.eye(4))


def test_dicom_off_loopback_needs_an_allow_list() -> None:
    with pytest.raises(ConfigError, match=r"dicom\.allowed_calling_ae_titles"):
        load_settings(None, {"dicom.enabled": True, "dicom.host": "0.0.0.0"})
    s = load_settings(
        None, {"dicom.enabled": True, "dicom.host": "0.0.0.0", "dicom.allowed_calling_ae_titles": ["OARM"]}
    )
    assert s.dicom.allowed_calling_ae_titles == ("OARM",)
    assert load_settings(None, {"dicom.enabled": True, "dicom.host": "10.0.0.2",
                                "dicom.allowed_peer_addresses": ["10.0.0.0/24"]}).dicom.enabled  # fmt: skip


def test_igtl_off_loopback_needs_peer_addresses_and_bad_entries_are_named() -> None:
    with pytest.raises(ConfigError, match=r"igtl\.allowed_peer_addresses"):
        load_settings(None, {"igtl.enabled": True, "igtl.host": "0.0.0.0"})
    with pytest.raises(ConfigError, match=r"igtl\.allowed_peer_addresses.*not-an-ip"):
        load_settings(None, {"igtl.allowed_peer_addresses": ["not-an-ip"]})
    with pytest.raises(ConfigError, match=r"dicom\.ae_title"):
        load_settings(None, {"dicom.ae_title": "X" * 17})


def test_non_loopback_api_needs_token_and_tls_unless_insecure_is_allowed(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"tls\.cert_file"):
        load_settings(None, {"host": "0.0.0.0", "api_token": TOKEN})
    cert, key = tmp_path / "c.pem", tmp_path / "k.pem"
    cert.write_text("x")
    key.write_text("y")
    assert load_settings(None, {"host": "0.0.0.0", "api_token": TOKEN, "tls.cert_file": cert,
                                "tls.key_file": key}).tls.enabled  # fmt: skip
    with pytest.raises(ConfigError, match="set together"):
        load_settings(None, {"tls.cert_file": cert})
    with pytest.raises(ConfigError, match="not a readable file"):
        load_settings(None, {"tls.cert_file": tmp_path / "nope.pem", "tls.key_file": key})


def test_unloadable_certificate_fails_at_start_up(tmp_path: Path) -> None:
    from service.errors import TlsConfigError
    from service.http.tls import uvicorn_ssl_options

    cert, key = tmp_path / "c.pem", tmp_path / "k.pem"
    cert.write_text("not a certificate")
    key.write_text("not a key")
    s = load_settings(None, {"tls.cert_file": cert, "tls.key_file": key})
    with pytest.raises(TlsConfigError, match="cannot be loaded"):
        uvicorn_ssl_options(s)
    assert uvicorn_ssl_options(load_settings(None)) == {}


def test_tool0_from_tcp_and_serve_flags() -> None:
    import argparse

    from service.cli.commands.serve import add_arguments, settings_from_args

    p = argparse.ArgumentParser()
    add_arguments(p)
    s = settings_from_args(p.parse_args(["--dicom-port", "0", "--igtl-port", "0"]))
    assert s.dicom.enabled and s.dicom.port == 0 and s.igtl.enabled and s.igtl.port == 0
    s = load_settings(None, {"igtl.tool0_from_tcp": {"translation_mm": (0, 0, 100), "rpy_deg": (0, 0, 0)}})
    np.testing.assert_allclose(s.igtl.tool0_from_tcp.matrix()[:3, 3], [0, 0, 100])
