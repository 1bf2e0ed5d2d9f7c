"""The OpenIGTLink publisher's view of the orchestrator's registration (issue #31): only an
accepted registration that is current is ever served; anything else (none, withdrawn, retired,
a verification's withdrawal) is INVALID with the orchestrator's reason, so the server sends a
STATUS and no matrix.  The orchestrator here is a plain holder of the two attributes the publisher
reads (``current``, ``no_current_reason``); the server is not started."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest

from registration.model.kinematics import RobotModel
from service.navigation.igtl.publisher import IgtlPublisher
from service.navigation.igtl.server import registration_messages, tool_messages
from service.records import RegistrationRecord
from service.settings import IgtlSettings

IMAGE_FROM_ROBOT = (
    (0.0, -1.0, 0.0, 10.0),
    (1.0, 0.0, 0.0, 20.0),
    (0.0, 0.0, 1.0, 30.0),
    (0.0, 0.0, 0.0, 1.0),
)
ACCEPTED = RegistrationRecord(
    created_at="2026-01-01T00:00:00+00:00", status="accepted", config_hash="h", software_version="t",
    id=7, image_from_robot=IMAGE_FROM_ROBOT, fre_mm=0.3, is_current=True,
)  # fmt: skip


@dataclass
class OrchestratorState:
    current: RegistrationRecord | None
    no_current_reason: str = ""
    phantom: Any = None
    robot_model: Any = None
    tool0_from_phantom: Any = None


def publisher(state: OrchestratorState) -> IgtlPublisher:
    return IgtlPublisher(IgtlSettings(), state, None, None, RobotModel.load("tx60"), lambda e: None)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("record", "reason", "want"),
    [
        (
            None,
            "registration 7 was withdrawn: verification 3 failed (max 2.05 mm > 1 mm)",
            "verification 3 failed",
        ),
        (None, "", "no current registration"),
        (
            replace(ACCEPTED, status="withdrawn", reason="scan changed", withdrawn_at="2026"),
            "",
            "is withdrawn",
        ),
        (replace(ACCEPTED, status="retired", reason="calibration 2 activated"), "", "is retired"),
    ],
)
def test_a_registration_not_accepted_and_current_is_invalid_with_its_reason(
    record: RegistrationRecord | None, reason: str, want: str
) -> None:
    pub = publisher(OrchestratorState(record, reason))
    state = pub._registration_state()
    assert state.current is None
    cfg = IgtlSettings()
    for out in [*registration_messages(state, cfg), *tool_messages(state, None, pub.server.source, cfg, 0.0)]:
        assert out.type == "STATUS" and out.metadata["TransformStatus"] == "INVALID"
        assert want in out.metadata["Reason"], out.metadata["Reason"]


def test_the_accepted_current_registration_is_served(phantom: Any) -> None:
    state = publisher(OrchestratorState(ACCEPTED, phantom=phantom))._registration_state()
    assert state.current is not None and state.current.registration_id == "7"
    np.testing.assert_array_equal(state.current.image_from_robot, np.asarray(IMAGE_FROM_ROBOT))
    out = registration_messages(state, IgtlSettings())
    assert [o.type for o in out] == ["TRANSFORM"] and out[0].metadata["TransformStatus"] == "OK"
