"""dicomnet.scu: the reactor of an SCU association takes requests, never a response."""

from __future__ import annotations

from pynetdicom import AE
from pynetdicom.association import Association
from pynetdicom.dimse_primitives import C_ECHO, C_STORE

from dicomnet.scu import keep_responses_for_the_caller


def _response() -> C_STORE:
    rsp = C_STORE()
    rsp.MessageIDBeingRespondedTo = 1
    rsp.Status = 0x0000
    return rsp


def _request() -> C_ECHO:
    req = C_ECHO()
    req.MessageID = 7
    req.AffectedSOPClassUID = "1.2.840.10008.1.1"
    return req


def _association() -> Association:
    assoc = Association(AE(), "requestor")
    keep_responses_for_the_caller(assoc.dimse)
    return assoc


def test_a_response_stays_queued_for_the_waiting_caller() -> None:
    dimse = _association().dimse
    rsp = _response()
    dimse.msg_queue.put((1, rsp))
    assert dimse.get_msg(block=False) == (None, None)  # the reactor's non-blocking read
    assert dimse.msg_queue.qsize() == 1
    assert dimse.get_msg(block=True) == (1, rsp)  # send_c_store's blocking read


def test_a_request_is_still_served_by_the_reactor() -> None:
    dimse = _association().dimse
    req = _request()
    dimse.msg_queue.put((3, req))
    assert dimse.get_msg(block=False) == (3, req)
    assert dimse.get_msg(block=False) == (None, None)  # empty queue
