"""``GET /`` (the page), ``/static/{file}``, ``/favicon.ico`` and ``/docs`` (Swagger UI shell).

The files come from the package (``importlib.resources``), read once into memory at router
creation: a request names a file from that fixed table or gets 404, so no request path ever
reaches the file system.  Nothing here needs the token (the page signs in on its own; every data
route it calls does), and nothing here is in the OpenAPI schema.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from importlib import resources

from fastapi import APIRouter, Request, Response

from service.errors import NotFoundError

STATIC_PREFIX = "/static/"
MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".txt": "text/plain; charset=utf-8",
}
"""The only file kinds served; anything else in the folder (LICENSE, NOTICE) as text/plain."""


@dataclass(frozen=True)
class Asset:
    body: bytes
    media_type: str
    etag: str


def load_assets() -> dict[str, Asset]:
    """Every file under ``service/http/web/static`` by its path relative to that folder (``swagger/x.js``)."""
    root = resources.files("service.http.web").joinpath("static")
    out: dict[str, Asset] = {}

    def walk(node: resources.abc.Traversable, prefix: str) -> None:
        for child in node.iterdir():
            name = prefix + child.name
            if child.is_dir():
                walk(child, name + "/")
            elif child.is_file() and not child.name.startswith("."):
                body = child.read_bytes()
                suffix = "." + child.name.rsplit(".", 1)[-1] if "." in child.name else ""
                media = MEDIA_TYPES.get(suffix, "text/plain; charset=utf-8")
                out[name] = Asset(body, media, '"' + hashlib.sha256(body).hexdigest()[:16] + '"')

    walk(root, "")
    return out


def _answer(request: Request, asset: Asset, cache: str) -> Response:
    headers = {"ETag": asset.etag, "Cache-Control": cache, "X-Content-Type-Options": "nosniff"}
    if request.headers.get("if-none-match") == asset.etag:
        return Response(status_code=304, headers=headers)
    return Response(asset.body, media_type=asset.media_type, headers=headers)


def build_router(*, docs: bool) -> APIRouter:
    """The page's routes; ``docs=False`` (``api.docs``) leaves ``/docs`` and its assets out."""
    assets = load_assets()
    if not docs:
        assets = {k: v for k, v in assets.items() if not k.startswith("swagger/")}
    router = APIRouter(include_in_schema=False)
    # the page and the docs shell are re-validated on every load (ETag), assets likewise: a new
    # release must never run against an old script in the OR's browser cache
    revalidate = "no-cache"

    @router.get("/")
    def page(request: Request) -> Response:
        return _answer(request, assets["index.html"], revalidate)

    @router.get("/favicon.ico")
    def favicon(request: Request) -> Response:
        return _answer(request, assets["favicon.svg"], revalidate)

    @router.get(STATIC_PREFIX + "{name:path}")
    def static(request: Request, name: str) -> Response:
        asset = assets.get(name)
        if asset is None or name in ("index.html", "docs.html"):
            raise NotFoundError(f"no static file {name[:80]!r}")
        return _answer(request, asset, revalidate)

    if docs:

        @router.get("/docs")
        def docs_page(request: Request) -> Response:
            return _answer(request, assets["docs.html"], revalidate)

    return router
