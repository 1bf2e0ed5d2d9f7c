"""The API token rule (:mod:`service.token_strength`) on random tokens: how low they score and how
many it would refuse.

Draws ``--n`` tokens of each kind (``secrets.token_urlsafe(16)``, ``token_hex(16)``,
``token_urlsafe(32)`` as ``oarmreg token`` prints) and the hardest case for the rule: 22
characters from the ``token_urlsafe`` alphabet without upper case (what a ``token_urlsafe(16)``
is with probability 2·(38/64)^22 ≈ 2·10^-5: all its letters one case).  Prints the lowest estimate
and the count refused of each.

Run: ``.venv/bin/python -m benchmarks.bench_token_strength [--n 200000]``
"""

from __future__ import annotations

import argparse
import secrets
import string
from collections.abc import Callable

from service.token_strength import MIN_TOKEN_BITS, estimated_bits, token_problem

SINGLE_CASE = string.ascii_lowercase + string.digits + "-_"


def _single_case_22() -> str:
    return "".join(secrets.choice(SINGLE_CASE) for _ in range(22))


KINDS: dict[str, Callable[[], str]] = {
    "token_urlsafe(16)": lambda: secrets.token_urlsafe(16),
    "token_hex(16)": lambda: secrets.token_hex(16),
    "token_urlsafe(32)": lambda: secrets.token_urlsafe(32),
    "22 chars, one letter case": _single_case_22,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=200_000)
    args = parser.parse_args()
    print(f"rule: token_strength.token_problem, threshold {MIN_TOKEN_BITS:.0f} estimated bits")
    for name, draw in KINDS.items():
        tokens = [draw() for _ in range(args.n)]
        low = min(estimated_bits(t) for t in tokens)
        refused = sum(1 for t in tokens if token_problem(t) is not None)
        print(f"{name:28s} n={args.n}  lowest {low:6.1f} bits  refused {refused}")


if __name__ == "__main__":
    main()
