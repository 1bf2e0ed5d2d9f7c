"""How an error is answered (service/error_map.py, service/errors.py), tested on its own.

Issue #35, "one error design": every exception class under ``service/`` lives in
``service/errors.py``; each class's HTTP status and exit code are stated once (in its own body, or
for a family of ``registration``/``drivers`` in ``ERROR_MAP``), its title once (its class); a service
error never takes its status from a domain parent chosen for another reason."""

from __future__ import annotations

import ast
import builtins
import inspect
import re
from pathlib import Path

import pytest

from drivers import errors as drv
from drivers.errors import LinkConfigError, RobotLinkError
from registration import errors as reg
from service import error_map as em
from service import errors as svc

ROOT = Path(__file__).resolve().parents[3]
DOCS_CLI = ROOT / "docs" / "cli.md"
ERRORS_MODULE = ROOT / "service" / "errors.py"


def error_classes(module: object) -> list[type[BaseException]]:
    """The exception classes ``module`` defines (not those it imports)."""
    return [
        c
        for c in vars(module).values()
        if inspect.isclass(c)
        and issubclass(c, BaseException)
        and c.__module__ == getattr(module, "__name__", "")
    ]


SERVICE_ERRORS = error_classes(svc)
DOMAIN_ERRORS = error_classes(reg) + error_classes(drv)


@pytest.mark.parametrize(
    ("exc", "http", "exit_code", "title"),
    [
        # a family of registration/drivers: its row in the table, its class's title
        (reg.AccuracyGateError("FRE"), 409, em.EXIT_ACCURACY, "Accuracy gate failed"),
        (RobotLinkError("down"), 409, em.EXIT_ROBOT_LINK, "Robot link error"),
        (LinkConfigError("bad url"), 422, em.EXIT_CONFIG, "Invalid robot link configuration"),
        # a domain subclass without a row: its nearest family's row, its own title
        (reg.RobotMovedError("moved"), 409, em.EXIT_REFUSED, "Robot moved during the scan"),
        (reg.JointHistoryIncompleteError("gap"), 409, em.EXIT_REFUSED, "Joint history incomplete"),
        (reg.TooFewWithinGateError("3 of 8"), 409, em.EXIT_REFUSED, "Too few spheres within the gate"),
        (reg.PhantomDefinitionError("bad"), 422, em.EXIT_CONFIG, "Invalid phantom definition"),
        (reg.PosesFileError("bad"), 422, em.EXIT_INPUT, "Invalid poses file"),
        # a service error: what its own body states
        (svc.StorageFullError("full"), 507, em.EXIT_CONFIG, "Data folder full"),
        (svc.NoCurrentRegistrationError("none"), 409, em.EXIT_REFUSED, "No current registration"),
        (svc.QaProtocolError("no such pose"), 422, em.EXIT_INPUT, "QA protocol problem"),
        (svc.QaProtocolNameTakenError("taken"), 409, em.EXIT_INPUT, "QA protocol name taken"),
        (svc.SroUnavailableError("refused"), 409, em.EXIT_REFUSED, "Spatial Registration object unavailable"),
        (svc.UnauthorizedError("no token"), 401, em.EXIT_USAGE, "Unauthorized"),
        (svc.UsageError("--a needs --b"), 422, em.EXIT_USAGE, "Usage error"),
        (svc.IgtlCrcError("crc"), 500, em.EXIT_INPUT, "OpenIGTLink CRC mismatch"),
    ],
)
def test_an_error_is_answered_by_the_nearest_class_that_states_it(
    exc: Exception, http: int, exit_code: int, title: str
) -> None:
    assert (em.http_status_of(exc), em.exit_code_of(exc), em.title_of(exc)) == (http, exit_code, title)


def test_a_subclass_defined_elsewhere_takes_the_nearest_statement_not_the_roots() -> None:
    class LateRefusal(reg.JointHistoryIncompleteError):
        title = ""  # no title of its own: the nearest ancestor's

    class LateNotFound(svc.NotFoundError):
        pass

    e = LateRefusal("history")
    assert em.classify(e) is em.ERROR_MAP[reg.RegistrationError]
    assert em.title_of(e) == "Joint history incomplete"
    assert em.exit_code_of(e) == em.EXIT_REFUSED
    assert (em.http_status_of(LateNotFound("x")), em.title_of(LateNotFound("x"))) == (404, "Not found")


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


# ---- one error design (issue #35) -----------------------------------------------------------


def exception_classes_in(sources: dict[str, str], known: set[str]) -> list[str]:
    """``name:line Class`` for each class of ``sources`` (name → text) deriving from a class named in
    ``known`` or from such a class of any of the sources, by the last part of the base's name (so
    ``wire.IgtlWireError`` counts)."""
    classes = [
        (name, node)
        for name, text in sources.items()
        for node in ast.walk(ast.parse(text))
        if isinstance(node, ast.ClassDef)
    ]

    def bases(c: ast.ClassDef) -> set[str]:
        return {ast.unparse(b).rsplit(".", 1)[-1] for b in c.bases}

    names = set(known)
    grown = True
    while grown:
        new = {c.name for _, c in classes if bases(c) & names}
        grown = not new <= names
        names |= new
    return [f"{name}:{c.lineno} {c.name}" for name, c in classes if bases(c) & names]


def test_the_scan_finds_stray_error_classes() -> None:
    """The scan is not vacuous: it sees the shapes the old code had."""
    sources = {
        "a.py": "class A(Exception): ...\nclass B(A): ...\nclass C(x.ConfigError): ...\nclass D: ...\n",
        "b.py": "class E(a.B): ...\n@dataclass\nclass A: ...\n",
    }
    assert exception_classes_in(sources, {"Exception", "ConfigError"}) == [
        "a.py:1 A",
        "a.py:2 B",
        "a.py:3 C",
        "b.py:1 E",
    ]


def test_every_exception_class_of_the_service_lives_in_service_errors() -> None:
    """Listener-internal errors too (the OpenIGTLink framing, a DICOM instance not stored, a CLI
    usage error): they belong to the hierarchy docs/design.md describes."""
    known = {n for n, v in vars(builtins).items() if isinstance(v, type) and issubclass(v, BaseException)}
    known |= {c.__name__ for c in SERVICE_ERRORS + DOMAIN_ERRORS}
    sources = {
        str(path.relative_to(ROOT)): path.read_text(encoding="utf-8")
        for path in sorted((ROOT / "service").rglob("*.py"))
        if path != ERRORS_MODULE
    }
    assert exception_classes_in(sources, known) == []


def test_every_service_error_derives_from_a_family_and_names_its_title() -> None:
    assert [c.__name__ for c in SERVICE_ERRORS if not issubclass(c, em.FAMILIES)] == []
    assert [c.__name__ for c in SERVICE_ERRORS if not vars(c).get("title")] == []


def test_a_service_error_never_takes_its_status_from_a_domain_parent() -> None:
    """The nearest class stating a service error's (status, exit code) is a service error: never a
    family of registration/drivers chosen for its meaning there (the old ``SroUnavailableError``
    answered 409 because it was made a ``RegistrationError``)."""

    def stating(cls: type) -> type:
        return next(c for c in cls.__mro__ if em.stated_by(c) is not None)

    borrowed = {c.__name__: stating(c).__name__ for c in SERVICE_ERRORS if stating(c) not in SERVICE_ERRORS}
    assert borrowed == {}


def test_each_answer_is_stated_once() -> None:
    """Status and exit code on the class or in the table, never both; both or neither in a body;
    no title in the table (the class holds it)."""
    assert [f.name for f in em.ErrorClass.__dataclass_fields__.values()] == ["http_status", "exit_code"]
    both = [c.__name__ for c in em.ERROR_MAP if "http_status" in vars(c) or "exit_code" in vars(c)]
    assert both == []
    halves = [c.__name__ for c in SERVICE_ERRORS if ("http_status" in vars(c)) != ("exit_code" in vars(c))]
    assert halves == []
    assert [c.__name__ for c in em.ERROR_MAP if not vars(c).get("title")] == []


def test_registration_and_drivers_know_nothing_of_http() -> None:
    stated = [
        f"{c.__module__}.{c.__name__}" for c in DOMAIN_ERRORS if {"http_status", "exit_code"} & set(vars(c))
    ]
    assert stated == []


def test_every_exit_code_is_documented_in_the_module_and_docs_cli() -> None:
    codes = {v for k, v in vars(em).items() if k.startswith("EXIT_")}
    in_docstring = {int(m) for m in re.findall(r"^(\d)\s{2,}\S", em.__doc__ or "", re.M)}
    text = DOCS_CLI.read_text(encoding="utf-8")
    paragraph = text[text.index("Exit codes:") :].split("\n\n", 1)[0]
    in_docs = {int(m) for m in re.findall(r"(?:^|·|:)\s*(\d+) [a-z]", paragraph)}
    assert codes == in_docstring == in_docs, (codes, in_docstring, in_docs)
    answers = [em.classify(c.__new__(c)) for c in SERVICE_ERRORS] + list(em.ERROR_MAP.values())
    assert all(a is not None and a.exit_code in codes for a in answers)


def test_the_problem_types_clients_see_are_the_class_names() -> None:
    """The gate's refusals kept the ``type`` they had when the gate built them by hand, and a route's
    401/503 now carries the same ``type`` as the gate's (not ``auth`` / ``database-gone``)."""
    from service.http.api.problems import problem_kind

    kinds = {
        problem_kind(cls("x"))
        for cls in (
            svc.HostNotAllowedError,
            svc.OriginNotAllowedError,
            svc.UnauthorizedError,
            svc.ReadOnlyTokenError,
            svc.UnsupportedMediaTypeError,
            svc.BadRequestError,
            svc.BodyTooLargeError,
            svc.DatabaseUnavailableError,
        )
    }
    kinds.add(problem_kind(svc.AuthThrottledError("x", retry_after_s=1)))
    assert kinds == {
        "host-not-allowed",
        "origin-not-allowed",
        "unauthorized",
        "read-only-token",
        "unsupported-media-type",
        "bad-request",
        "body-too-large",
        "database-unavailable",
        "auth-throttled",
    }
