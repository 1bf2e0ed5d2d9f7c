"""API tokens for tests: random, as the strength rule (:mod:`service.token_strength`) demands.

Tests never hard-code a token: a patterned one (``test-token-0123456789``) is refused at start-up.
"""

from __future__ import annotations

import secrets


def make_token() -> str:
    """A fresh random API token (``secrets.token_urlsafe(32)``, as ``oarmreg token`` prints)."""
    return secrets.token_urlsafe(32)
