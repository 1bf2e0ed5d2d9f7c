"""OpenIGTLink push of the registration and the live tool pose.

:mod:`service.navigation.igtl.wire` is the pure wire format; :mod:`service.navigation.igtl.server` the asyncio
server that fans transforms out to any number of clients.
"""
