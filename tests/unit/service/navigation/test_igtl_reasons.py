"""``ToolToImage`` has one freshness limit, named in its reason; a long ``Reason`` is cut at a word
with the whole text on ``/status``; docs/slicer.md names the tool that decodes STATUS (issue 42,
item 6)."""

from __future__ import annotations

from service.navigation.igtl.publisher import FULL_TEXT_NOTE, REASON_MAX_CHARS, cut_at_word, joint_view
from service.navigation.igtl.server import tool_messages
from service.settings import IgtlSettings
from tests.helpers.paths import REPO

Q = (0.0, 0.0, 1.57, 0.0, 0.78, 0.0)


def test_a_link_stale_by_the_drivers_rule_is_fresh_within_joint_max_age() -> None:
    """The driver calls a 60 ms gap stale; ToolToImage judges only igtl.joint_max_age_s (0.25 s)."""
    cfg = IgtlSettings()
    fresh = joint_view(
        Q, 10.0, "stale", "no valid joint frame for 0.080 s (> 0.06 s)", 10.08, cfg.joint_max_age_s
    )
    assert fresh.health == "connected"
    old = joint_view(
        Q, 10.0, "stale", "no valid joint frame for 0.300 s (> 0.06 s)", 10.3, cfg.joint_max_age_s
    )
    assert old.health == "stale"
    assert old.reason == f"no joint sample for 0.300 s (> igtl.joint_max_age_s = {cfg.joint_max_age_s:g} s)"
    down = joint_view(Q, 10.0, "down", "connection refused", 10.01, cfg.joint_max_age_s)
    assert (down.health, down.reason) == ("down", "connection refused")


def test_the_tool_status_names_the_limit() -> None:
    import numpy as np

    from service.navigation.igtl.server import IgtlStateSource, RegistrationState, RegistrationView

    cfg = IgtlSettings()
    view = RegistrationView(np.eye(4), "7", 0.1, None, None, "", (), 4.0)
    source = IgtlStateSource(lambda: RegistrationState(view), lambda: None, lambda q: np.eye(4), np.eye(4))
    joints = joint_view(Q, 10.0, "connected", "", 10.3, cfg.joint_max_age_s)
    (status,) = tool_messages(RegistrationState(view), joints, source, cfg, 10.3)
    assert status.type == "STATUS" and "igtl.joint_max_age_s = 0.25 s" in status.metadata["Reason"]


def test_a_long_reason_is_cut_at_a_word_and_points_to_status() -> None:
    words = "registration 12 was withdrawn: verification 4 of scan 9 failed with a maximum error of 3.1 mm"
    text = " ".join([words] * 12)
    cut = cut_at_word(text)
    assert len(cut) <= REASON_MAX_CHARS and cut.endswith(FULL_TEXT_NOTE)
    kept = cut.removesuffix(FULL_TEXT_NOTE)
    assert text.startswith(kept) and text[len(kept)] == " "  # ends at a word boundary
    assert cut_at_word(words) == words


def test_slicer_doc_names_the_tool_that_decodes_status() -> None:
    import pyigtl

    assert not hasattr(pyigtl, "StatusMessage")  # so pyigtl cannot be what checks STATUS
    text = " ".join((REPO / "docs" / "slicer.md").read_text(encoding="utf-8").split())
    assert "pyigtl cannot decode STATUS" in text and "igtl::StatusMessage" in text
