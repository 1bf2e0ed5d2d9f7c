"""Pick the link class from the URL scheme: one static table, no registration by import.

::

    link = open_link("simple-message://192.168.0.254:11002")   # built, not connected
    await link.connect(timeout_s=5.0)

The link modules import :mod:`drivers.base`; :mod:`drivers.base` imports none of them,
and this module imports all of them, so there is no import cycle.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any
from urllib.parse import urlsplit

from drivers.base import BaseLink
from drivers.errors import LinkConfigError
from drivers.modbus import ModbusLink
from drivers.serial_link import SerialLink
from drivers.simple_message import SimpleMessageLink

SCHEMES: Mapping[str, Callable[..., BaseLink]] = {
    SimpleMessageLink.scheme: SimpleMessageLink,  # simple-message://HOST[:11002]
    ModbusLink.scheme: ModbusLink,  # modbus://HOST[:502]?unit=…&fc=…&address=…
    SerialLink.scheme: SerialLink,  # serial:///dev/ttyS0?baudrate=115200
}
"""URL scheme → link class (design.md §6)."""


def open_link(url: str, **options: Any) -> BaseLink:
    """Build (never connect) the link for ``url``.

    ``simple-message://HOST[:11002]``, ``modbus://HOST[:502]?…``,
    ``serial:///dev/ttyS0?baudrate=115200``.  ``options`` are passed to the
    link's constructor (e.g. ``stale_after_s=0.1``) and override the URL query.

    Raises
    ------
    LinkConfigError
        Unknown scheme or malformed URL / options.
    """
    scheme = urlsplit(url).scheme
    factory = SCHEMES.get(scheme)
    if factory is None:
        raise LinkConfigError(
            f"unknown robot link scheme {scheme!r} in {url!r}; expected one of "
            f"{sorted(SCHEMES)} (e.g. simple-message://192.168.0.254:11002)"
        )
    try:
        return factory(url, **options)
    except TypeError as e:
        raise LinkConfigError(f"{url}: bad link option ({e})") from None
