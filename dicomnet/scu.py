"""pynetdicom SCU associations whose responses cannot be stolen by their own reactor thread.

pynetdicom (3.0.4, the newest) runs a reactor thread beside every association. It takes any
decoded DIMSE message off the queue with ``dimse.get_msg(block=False)`` and serves it as a request.
``send_c_store`` pauses the reactor before it waits for its response, but the pause has a window:
the reactor may already be past its checkpoint and about to read the queue. When the response
lands in that window the reactor takes it ("Received unexpected C-STORE service message") and the
caller waits ``dimse_timeout`` for a response that never comes, then aborts the association.
We saw it in CI on a loaded 2-core machine: the first C-STORE of a series returned no status and
the SCP recorded the association as aborted. The race is known upstream (pynetdicom #435, #875).

:func:`associate` opens the association as ``AE.associate`` does, then lets its reactor take
only *requests* off the queue. Responses stay queued for the ``send_*`` call waiting on them. An
SCU association never receives a request, so nothing the reactor should serve is held back.
Used by the PACS export, the mock O-arm's push and the test peers; in :mod:`dicomnet` (not in
``service/``) because the mocks use it and may not import ``service``.  Was ``drivers/dicom_scu.py``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pynetdicom import AE
    from pynetdicom.association import Association
    from pynetdicom.dimse import DIMSEServiceProvider


def keep_responses_for_the_caller(dimse: DIMSEServiceProvider) -> None:
    """Make ``dimse.get_msg(block=False)`` (only the reactor calls it) return requests only."""
    take = dimse.get_msg

    def get_msg(block: bool = False) -> Any:
        if not block:
            _, msg = dimse.peek_msg()
            if msg is None or not msg.is_valid_request:
                return None, None
        return take(block)

    dimse.get_msg = get_msg  # type: ignore[method-assign]


def associate(ae: AE, host: str, port: int, **kwargs: Any) -> Association:
    """``ae.associate(host, port, **kwargs)`` with :func:`keep_responses_for_the_caller` applied."""
    assoc = ae.associate(host, port, **kwargs)
    keep_responses_for_the_caller(assoc.dimse)
    return assoc
