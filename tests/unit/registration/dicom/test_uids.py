"""The one DICOM UID check (PS3.5 §9.1), drawn against the rule itself and against pydicom's."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydicom.uid import UID

from registration.dicom.uids import MAX_UID_CHARS, is_dicom_uid

COMPONENT = st.one_of(st.just("0"), st.from_regex(r"[1-9][0-9]{0,7}", fullmatch=True))
UIDS = st.lists(COMPONENT, min_size=1, max_size=12).map(".".join)


@pytest.mark.filterwarnings("ignore:The value length")  # pydicom's, for the UIDs over 64 characters drawn
@given(UIDS)
def test_components_joined_by_dots_are_a_uid_up_to_64_characters(uid: str) -> None:
    assert is_dicom_uid(uid) == (len(uid) <= MAX_UID_CHARS)
    assert is_dicom_uid(uid) == UID(uid).is_valid


@given(UIDS, st.sampled_from(["\n", " ", "/", "..", "a", "\x00", "-1"]), st.integers(0, 3))
def test_anything_else_in_it_is_refused(uid: str, junk: str, where: int) -> None:
    """Including a trailing newline, which pydicom's ``UID.is_valid`` accepts (``$`` matches before
    it) and which the SCP would have made part of a folder name."""
    cut = [0, len(uid) // 2, len(uid), len(uid)][where]
    bad = uid[:cut] + junk + uid[cut:]
    assert not is_dicom_uid(bad)


def test_leading_zeros_and_empty_components_are_not_a_uid() -> None:
    for bad in ["", "01.2", "1..2", "1.2.", ".1", "1.02"]:
        assert not is_dicom_uid(bad), bad
    assert is_dicom_uid("1.2.0.3") and is_dicom_uid("0")
    with pytest.warns(UserWarning, match="Invalid value for VR UI"):  # pydicom warns, yet:
        assert UID("1.2.3\n").is_valid  # why the check is not pydicom's
