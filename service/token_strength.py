"""How guessable an API token is: a conservative entropy estimate and the rule the settings apply.

The rule (:func:`token_problem`): a token is accepted when it is at least
:data:`MIN_TOKEN_CHARS` characters long **and** its estimated entropy is at least
:data:`MIN_TOKEN_BITS` bits.  ``oarmreg token`` prints one that passes
(``secrets.token_urlsafe(32)``: 43 characters, 256 random bits).

The estimate (:func:`estimated_bits`) counts what an attacker who knows the usual shapes of
hand-made tokens still has to guess, character by character:

* a character is worth ``log2(alphabet)`` bits, the alphabet being the summed size of the
  character classes the token uses (lower case 26, upper case 26, digits 10, ``-`` / ``_`` 2,
  other printable 32: a ``token_urlsafe`` token has 64); a token of hex digits only has 16;
* a character that repeats the previous one or steps by one from it (``aaaa``, ``0123``,
  ``fedc``), is next to it on a keyboard row (``qwerty``, ``asdf``; not in hexadecimal tokens),
  belongs to a piece of 3 characters seen earlier (the whole piece: ``Xk9#mQ2!`` × 3 is worth one
  copy), or is a separator used before (the second ``-``) is worth :data:`PATTERN_BITS`;
* a year 1950–2039 standing alone between non-digits (``Surgery2026``) is worth :data:`YEAR_BITS`
  in all;
* in a token whose letters are all of one case (random tokens mix cases), a piece of
  :data:`WORD_MIN_CHARS` or more letters between separators is read as a word and its letters are
  worth :data:`WORD_BITS` each (written English carries about 1 bit a letter, Shannon 1951).

It is a guard against hand-made tokens, not a proof of randomness: a token built to fool it
(camel-cased words, say) can pass.  Measured figures are in ``docs/security.md``.
"""

from __future__ import annotations

import math

MIN_TOKEN_CHARS = 22
"""Shortest accepted API token: ``secrets.token_urlsafe(16)`` (128 random bits) is 22 characters."""
MIN_TOKEN_BITS = 76.0
"""Least estimated entropy of an accepted token, bits.  Set between the two measured populations:
every hand-made token we tried (the project's former test tokens, ``my-super-secret-api-token-2024!``)
scores at most 72; of 100,000 draws each, ``token_urlsafe(16)`` scored at least 92.5 and
``token_hex(16)`` at least 80.0 (``python -m benchmarks.bench_token_strength``, docs/security.md)."""
TOKEN_COMMAND = "oarmreg token"
"""The command that prints a good token (named in every refusal)."""

_CLASSES: tuple[tuple[str, int], ...] = (
    ("lower", 26),
    ("upper", 26),
    ("digit", 10),
    ("urlsafe", 2),
    ("other", 32),
)
PATTERN_BITS = 1.0
"""What a character continuing a repeat, a ±1 run or an earlier piece is worth, bits."""
WORD_BITS = 1.0
"""What a letter of a word (:func:`_word_letters`) is worth, bits."""
WORD_MIN_CHARS = 3
MIN_WORDS = 2
"""Words are counted only in a token of at least this many (a random single-case token rarely
holds two letter-only pieces between separators; a hand-made one is usually words and dashes)."""
HEX_DIGITS = frozenset("0123456789abcdef")
REPEAT_MIN_CHARS = 3
KEYBOARD_ROWS = ("1234567890", "qwertyuiop", "asdfghjkl", "zxcvbnm")
"""Rows of a US/UK keyboard: a letter or digit next to the previous one on its row continues a
keyboard walk (``qwerty``, ``asdf``, ``0987``).  Not applied to hexadecimal tokens (machine-made)."""
YEAR_BITS = 7.0
"""What a year 1950–2039 standing alone between non-digits is worth, bits (90 years: log2 90 = 6.5)."""


def _class_of(ch: str) -> str:
    if "a" <= ch <= "z":
        return "lower"
    if "A" <= ch <= "Z":
        return "upper"
    if "0" <= ch <= "9":
        return "digit"
    if ch in "-_":
        return "urlsafe"
    return "other"


def is_hex(token: str) -> bool:
    """Only hexadecimal digits (``secrets.token_hex``, ``openssl rand -hex``)."""
    return all(c in HEX_DIGITS for c in token.lower())


def alphabet_size(token: str) -> int:
    """The summed size of the character classes ``token`` uses (64 for a ``token_urlsafe`` token;
    16 for a hexadecimal one)."""
    if is_hex(token):
        return 16
    used = {_class_of(c) for c in token}
    return sum(size for name, size in _CLASSES if name in used)


def _keyboard_neighbours(a: str, b: str) -> bool:
    """Are ``a`` and ``b`` next to each other on one row of :data:`KEYBOARD_ROWS` (either order)?"""
    a, b = a.lower(), b.lower()
    return any(a + b in row or b + a in row for row in KEYBOARD_ROWS)


def _patterned(token: str) -> list[bool]:
    """Per character: does it repeat / step from the previous one, walk the keyboard from it, or
    belong to a piece of :data:`REPEAT_MIN_CHARS` seen earlier (the whole piece, so ``abc!`` × 3
    costs only its first copy; in a hexadecimal token the piece's last character)?"""
    out = [False] * len(token)
    walks = not is_hex(token)
    for i in range(1, len(token)):
        step = ord(token[i]) - ord(token[i - 1])
        run = abs(step) <= 1 and _class_of(token[i]) == _class_of(token[i - 1])
        if run or (walks and _keyboard_neighbours(token[i - 1], token[i])):
            out[i] = True
    for i, ch in enumerate(token):
        if not ch.isalnum() and ch in token[:i]:  # a separator used again
            out[i] = True
    for i in range(REPEAT_MIN_CHARS - 1, len(token)):
        start = i - REPEAT_MIN_CHARS + 1
        if token[start : i + 1] in token[:i]:  # hexadecimal (machine-made): its last character only
            out[start if walks else i : i + 1] = [True] * (i + 1 - (start if walks else i))
    return out


def _year_digits(token: str) -> list[tuple[int, int]]:
    """Spans of years 1950–2039 standing alone between non-digits (``Surgery2026!``); none in a
    hexadecimal token, whose digit runs are random."""
    if is_hex(token):
        return []
    spans = []
    for i in range(len(token) - 3):
        piece = token[i : i + 4]
        alone = (i == 0 or not token[i - 1].isdigit()) and (i + 4 == len(token) or not token[i + 4].isdigit())
        if alone and piece.isdigit() and 1950 <= int(piece) <= 2039:
            spans.append((i, i + 4))
    return spans


def _word_letters(token: str) -> list[bool]:
    """Per character: is it in a word?  Only in a token whose letters are all of one case (random
    tokens mix cases; hex tokens have no words): a piece of :data:`WORD_MIN_CHARS` or more letters
    between separators (``-``, ``_``, ``.``, ...) or the token's ends, without digits: ``test`` in
    ``unit-test-token``, all of ``correcthorsebatterystaple``."""
    out = [False] * len(token)
    letters = [c for c in token if c.isascii() and c.isalpha()]
    if is_hex(token) or (any(c.islower() for c in letters) and any(c.isupper() for c in letters)):
        return out
    words: list[tuple[int, int]] = []
    start = 0
    for end in [*(i for i, c in enumerate(token) if not c.isalnum()), len(token)]:
        piece = token[start:end]
        if len(piece) >= WORD_MIN_CHARS and piece.isascii() and piece.isalpha():
            words.append((start, end))
        start = end + 1
    if len(words) >= MIN_WORDS:
        for a, b in words:
            out[a:b] = [True] * (b - a)
    return out


def estimated_bits(token: str) -> float:
    """A conservative entropy estimate of ``token``, bits (see the module docstring)."""
    if not token:
        return 0.0
    fresh = math.log2(alphabet_size(token))
    patterned = _patterned(token)
    words = _word_letters(token)
    bits = 0.0
    for a, b in _year_digits(token):
        if not any(patterned[a:b]):  # a repeated year is already counted as a repeat
            bits += YEAR_BITS - PATTERN_BITS * (b - a)  # its digits count PATTERN_BITS below
            patterned[a:b] = [True] * (b - a)
    for i in range(len(token)):
        if patterned[i]:
            bits += PATTERN_BITS
        elif words[i]:
            bits += min(WORD_BITS, fresh)
        else:
            bits += fresh
    return bits


def token_problem(token: str) -> str | None:
    """Why ``token`` can be guessed (one sentence naming the rule and ``oarmreg token``), or None."""
    bits = estimated_bits(token)
    if len(token) >= MIN_TOKEN_CHARS and bits >= MIN_TOKEN_BITS:
        return None
    return (
        f"it is {len(token)} characters with an estimated {bits:.0f} bits of entropy; the rule is at least "
        f"{MIN_TOKEN_CHARS} characters and {MIN_TOKEN_BITS:.0f} estimated bits (repeats, runs like 0123 "
        f"and word-like letter runs count little); make one with `{TOKEN_COMMAND}`"
    )
