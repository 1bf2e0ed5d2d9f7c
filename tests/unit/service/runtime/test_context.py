"""``ServiceContext`` is complete when built: no field filled in later, no ``None`` for a part that
always runs once the service has started (only the parts the settings switch off are Optional)."""

from __future__ import annotations

import dataclasses
import types
import typing

from service.runtime.context import ServiceContext

SWITCHABLE = {"watcher", "cstore", "igtl", "pacs", "auto_register"}
"""The parts the settings (or ``start_watcher=False``) can switch off."""
STATE = {"retention_problem"}
"""Not a part: what the retention loop found.  (What only HTTP keeps is ``service.http.state``.)"""


def _optional(tp: object) -> bool:
    return isinstance(tp, types.UnionType) and type(None) in typing.get_args(tp)


def test_every_field_is_given_at_construction() -> None:
    assert [f.name for f in dataclasses.fields(ServiceContext) if not f.init] == []


def test_only_the_switchable_parts_are_optional() -> None:
    hints = typing.get_type_hints(ServiceContext)
    optional = {name for name, tp in hints.items() if _optional(tp)}
    assert optional == SWITCHABLE | STATE
    required = {f.name for f in dataclasses.fields(ServiceContext) if f.default is dataclasses.MISSING}
    assert {"db", "capture", "orchestrator", "calibrations", "bus", "settings"} <= required
    assert required >= SWITCHABLE  # Optional, but said at construction, never left to a default
