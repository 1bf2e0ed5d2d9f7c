"""OpenIGTLink push of the registration and the live tool pose.

:mod:`service.navigation.igtl.wire` is the pure wire format; :mod:`service.navigation.igtl.server` the asyncio
server that fans transforms out to any number of clients.

Enters: the current registration and the live joints (:mod:`service.navigation.igtl.publisher`),
clients' queries.
Leaves: TRANSFORM / POINT / STATUS / CAPABILITY messages to every OpenIGTLink client.
"""
