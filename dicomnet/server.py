"""The listening side of a pynetdicom association, with two pynetdicom 3.0 defects worked around.

* :class:`PollAssociationSocket`: pynetdicom checks a socket for data with ``select``, which fails
  for a descriptor >= 1024; this one asks ``poll``.
* :class:`AssociationServer`: ``socketserver`` drops a failed ``accept`` (EMFILE) silently; this one
  reports it.

:func:`start_server` is ``ae.start_server(block=False)`` with both.  Nothing here knows what the
server stores or why: the service's Storage SCP (:mod:`service.intake.storage_scp`) is the one user,
and a test peer may be another.  It sits beside the client side
(:mod:`dicomnet.scu`).
"""

from __future__ import annotations

import errno
import select
import socket
import ssl
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

from pynetdicom.transport import AssociationSocket, RequestHandler, ThreadedAssociationServer
from pynetdicom.utils import make_target

if TYPE_CHECKING:
    from pynetdicom import AE


class PollAssociationSocket(AssociationSocket):
    """pynetdicom's association socket whose :attr:`ready` asks ``poll`` instead of ``select``.

    pynetdicom 3.0 checks for incoming data with ``select.select([sock], [], [], 0)``, which raises
    ``ValueError`` for a descriptor >= 1024 (FD_SETSIZE); pynetdicom takes that for a closed
    connection, so once the process holds more than 1024 descriptors (idle peers on the other
    listeners) every new association was aborted before its A-ASSOCIATE-RQ was read, silently.
    ``poll`` has no such limit; the answer is otherwise the same (readable, hung up or
    in error all mean "read now").  pynetdicom has no switch for this.  The listener itself uses
    ``socketserver``'s ``PollSelector`` already.
    """

    on_transport_error: Callable[[str], None] | None = None
    """Called (with the reason) when ``poll`` fails on an open socket: an internal failure, not a peer
    that closed."""

    @property
    def ready(self) -> bool:
        sock = self.socket
        if sock is None or self._is_connected is False:
            return False
        fd = sock.fileno()
        try:
            if fd < 0:
                raise OSError(errno.EBADF, "socket closed")
            poller = select.poll()
            poller.register(fd, select.POLLIN | select.POLLPRI)
            ready = bool(poller.poll(0))
        except (OSError, ValueError) as e:
            if fd >= 0 and self.on_transport_error is not None:
                self.on_transport_error(f"poll on descriptor {fd} failed ({e})")
            self.event_queue.put("Evt17")  # Evt17: transport connection closed (as pynetdicom does)
            return False
        if isinstance(sock, ssl.SSLSocket):  # buffered TLS data that poll cannot see (pynetdicom #528)
            return ready or bool(sock.pending())
        return ready


class PollRequestHandler(RequestHandler):
    """pynetdicom's request handler, its association on a :class:`PollAssociationSocket`."""

    def _create_association(self) -> Any:
        assoc = super()._create_association()
        sock = assoc.dul.socket
        if type(sock) is AssociationSocket:  # the same object and state, only ``ready`` differs
            sock.__class__ = PollAssociationSocket
            cast(PollAssociationSocket, sock).on_transport_error = getattr(
                self.server, "on_transport_error", None
            )
        return assoc


class AssociationServer(ThreadedAssociationServer):
    """pynetdicom's threaded server whose failed ``accept`` is reported (``socketserver`` drops it
    silently; EMFILE when the process is out of descriptors)."""

    on_accept_error: Callable[[OSError], None] | None = None
    on_transport_error: Callable[[str], None] | None = None

    def get_request(self) -> tuple[socket.socket, tuple[str, int]]:
        try:
            return super().get_request()
        except OSError as e:
            if self.on_accept_error is not None and e.errno not in (errno.EAGAIN, errno.EWOULDBLOCK):
                self.on_accept_error(e)
            raise


def start_server(
    ae: AE,
    address: tuple[str, int],
    handlers: list[Any],
    thread_name: str,
    *,
    on_accept_error: Callable[[OSError], None] | None = None,
    on_transport_error: Callable[[str], None] | None = None,
) -> AssociationServer:
    """``ae.start_server(address, block=False, evt_handlers=handlers)`` with :class:`AssociationServer`
    and :class:`PollRequestHandler` (pynetdicom's own non-blocking start takes neither).

    Serves on a daemon thread named ``thread_name``; ``server.shutdown()`` stops it.  Raises the
    ``OSError`` of a failed bind.
    """
    server = cast(AssociationServer, ae.make_server(
        address, evt_handlers=handlers, server_class=AssociationServer, request_handler=PollRequestHandler,
    ))  # fmt: skip
    server.on_accept_error = on_accept_error
    server.on_transport_error = on_transport_error
    thread = threading.Thread(target=make_target(server.serve_forever), name=thread_name, daemon=True)
    thread.start()
    ae._servers.append(server)  # as start_server does: server.shutdown() removes it there
    return server
