"""The API token strength rule (service/token_strength.py): random tokens pass, patterned ones are
refused by `config check` and `serve` (exit 3, naming the rule and `oarmreg token`)."""

from __future__ import annotations

import secrets
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from registration.errors import ConfigError
from service.cli.main import main
from service.settings import load_settings
from service.token_strength import MIN_TOKEN_BITS, MIN_TOKEN_CHARS, estimated_bits, token_problem

PATTERNED = [
    "aaaaaaaaaaaaaaaa",
    "passwordpassword",
    "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaa",  # long enough, no entropy
    "passwordpassword1234567",
    "correct_horse_battery_staple",
    "my-super-secret-api-token-2024!",
    "OARMREG_TOKEN_PRODUCTION_2026",
    # the test tokens this project used before the rule
    "fault-suite-token-0123456789abcdef",
    "or-integration-test-token-0123456789",
    "integration-test-token-0123456789",
    "bench-stillness-token-0123456789abcdef",
    "wall-display-token-0123456789abcdef",
    "t" * 24,
    # issue 41: a repeated random-looking piece, a keyboard walk, a word with a year twice
    "Xk9#mQ2!" * 3,
    "qwertyuiopasdfghjklzxcvbnm1234",
    "Surgery2026Surgery2026!!",
]


@settings(max_examples=100, deadline=None)
@given(nbytes=st.integers(min_value=16, max_value=64), readonly=st.booleans())
def test_random_urlsafe_tokens_always_pass(nbytes: int, readonly: bool) -> None:
    token = secrets.token_urlsafe(nbytes)  # the randomness is the point: not drawn by hypothesis
    assert token_problem(token) is None, (token, estimated_bits(token))
    key = "api_readonly_token" if readonly else "api_token"
    extra = {"api_token": secrets.token_urlsafe(16)} if readonly else {}
    s = load_settings(None, {key: token, **extra})
    assert getattr(s, key).get_secret_value() == token


@pytest.mark.parametrize("token", PATTERNED)
def test_patterned_tokens_are_refused_naming_the_rule(token: str) -> None:
    problem = token_problem(token)
    assert problem is not None
    assert f"at least {MIN_TOKEN_CHARS} characters and {MIN_TOKEN_BITS:.0f} estimated bits" in problem
    assert "oarmreg token" in problem
    for key in ("api_token", "api_readonly_token"):
        extra = {"api_token": secrets.token_urlsafe(16)} if key == "api_readonly_token" else {}
        with pytest.raises(ConfigError, match=rf"{key}.*can be guessed.*oarmreg token"):
            load_settings(None, {key: token, **extra})


def test_token_command_prints_a_token_that_passes(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["token"]) == 0
    token = capsys.readouterr().out.strip()
    assert len(token) == 43 and token_problem(token) is None
    assert main(["token", "--env", "OARMREG_API_TOKEN"]) == 0
    name, _, value = capsys.readouterr().out.strip().partition("=")
    assert name == "OARMREG_API_TOKEN" and value != token and token_problem(value) is None


def test_config_check_and_serve_refuse_a_guessable_token_with_exit_3(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("OARMREG_API_TOKEN", "passwordpassword")
    assert main(["config", "check"]) == 3
    err = capsys.readouterr().err
    assert "api_token" in err and "can be guessed" in err and "oarmreg token" in err
    serve = ["serve", "--port", "0", "--data", str(tmp_path / "d"), "--watch", str(tmp_path / "w")]
    assert main(serve) == 3
    err = capsys.readouterr().err
    assert "api_token" in err and "can be guessed" in err and "oarmreg token" in err
    assert not (tmp_path / "d").exists()  # refused before anything was created


@settings(max_examples=100, deadline=None)
@given(st.just(None))
def test_random_hex_tokens_always_pass(_: None) -> None:
    """Hexadecimal tokens (``token_hex(16)``) keep the one-character repeat rule and no keyboard walks:
    their lowest estimate over 100,000 draws is 80 bits (docs/security.md)."""
    token = secrets.token_hex(16)
    assert token_problem(token) is None, (token, estimated_bits(token))
