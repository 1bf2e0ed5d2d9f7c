"""The one table from error families to HTTP status, exit code and title (service/error_map.py),
tested on its own: until now only the API and CLI integration tests reached it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from drivers.errors import LinkConfigError, RobotLinkError
from registration import errors as reg
from service import error_map as em
from service import errors as svc

DOCS_CLI = Path(__file__).resolve().parents[3] / "docs" / "cli.md"


@pytest.mark.parametrize(
    ("exc", "http", "exit_code", "title"),
    [
        # a class in the table: its own row
        (reg.RobotMovedError("moved"), 409, em.EXIT_REFUSED, "Robot moved during the scan"),
        (reg.AccuracyGateError("FRE"), 409, em.EXIT_ACCURACY, "Accuracy gate failed"),
        (svc.StorageFullError("full"), 507, em.EXIT_CONFIG, "Data folder full"),
        (RobotLinkError("down"), 409, em.EXIT_ROBOT_LINK, "Robot link error"),
        # not in the table: its nearest ancestor's row (and its own title)
        (reg.TooFewWithinGateError("3 of 8"), 409, em.EXIT_REFUSED, "Too few spheres within the gate"),
        (reg.PhantomDefinitionError("bad"), 422, em.EXIT_CONFIG, "Invalid phantom definition"),
        (reg.PosesFileError("bad"), 422, em.EXIT_INPUT, "Invalid poses file"),
        (svc.NoCurrentRegistrationError("none"), 409, em.EXIT_REFUSED, "No current registration"),
        # a subclass with a row of its own beats its parent's
        (svc.QaProtocolNameTakenError("taken"), 409, em.EXIT_INPUT, "QA protocol name taken"),
        (LinkConfigError("bad url"), 422, em.EXIT_CONFIG, "Invalid robot link configuration"),
    ],
)
def test_an_error_is_answered_by_its_nearest_row(
    exc: Exception, http: int, exit_code: int, title: str
) -> None:
    assert (em.http_status_of(exc), em.exit_code_of(exc), em.title_of(exc)) == (http, exit_code, title)


def test_a_subclass_defined_elsewhere_takes_the_nearest_row_not_the_roots() -> None:
    class LateRefusal(reg.JointHistoryIncompleteError):
        title = ""  # no title of its own: the family's

    e = LateRefusal("history")
    assert em.classify(e) is em.ERROR_MAP[reg.JointHistoryIncompleteError]
    assert em.title_of(e) == "Joint history incomplete"
    assert em.exit_code_of(e) == em.EXIT_REFUSED


def test_an_instance_title_wins_over_the_class_and_the_family() -> None:
    e = reg.RegistrationError("x")
    e.title = "Scan changed while registering"
    assert em.title_of(e) == "Scan changed while registering"
    assert em.http_status_of(e) == 409


def test_an_error_that_is_not_ours_gets_the_documented_fallbacks() -> None:
    e = ValueError("not a service error")
    assert em.classify(e) is None
    assert (em.http_status_of(e), em.exit_code_of(e), em.title_of(e)) == (422, em.EXIT_INPUT, "Error")


def test_every_row_belongs_to_a_family() -> None:
    strays = [cls.__name__ for cls in em.ERROR_MAP if not issubclass(cls, em.FAMILIES)]
    assert strays == []


def test_every_exit_code_is_documented_in_the_module_and_docs_cli() -> None:
    codes = {v for k, v in vars(em).items() if k.startswith("EXIT_")}
    in_docstring = {int(m) for m in re.findall(r"^(\d)\s{2,}\S", em.__doc__ or "", re.M)}
    text = DOCS_CLI.read_text(encoding="utf-8")
    paragraph = text[text.index("Exit codes:") :].split("\n\n", 1)[0]
    in_docs = {int(m) for m in re.findall(r"(?:^|·|:)\s*(\d+) [a-z]", paragraph)}
    assert codes == in_docstring == in_docs, (codes, in_docstring, in_docs)
    assert all(row.exit_code in codes for row in em.ERROR_MAP.values())
