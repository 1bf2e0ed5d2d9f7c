"""Pure computation for O-arm ↔ Stäubli spatial registration.

No sockets, threads, watchers or logging configuration live here: arrays and
frozen dataclasses in, arrays and dataclasses out (design.md §2).
"""

__version__ = "0.1.0"
