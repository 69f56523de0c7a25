"""The browser pages: the viewer at ``/``, its static files, and the API docs served offline.

``/docs`` (Swagger UI) and ``/redoc`` are FastAPI's own pages (``get_swagger_ui_html``,
``get_redoc_html``, the self-hosting recipe of FastAPI's documentation) pointed at the copies of
Swagger UI and ReDoc vendored in the package, so they work without internet access. None of
these routes is part of the API schema.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from starlette.concurrency import run_in_threadpool

from service.errors import ApiError
from service.webassets import IMMUTABLE, REVALIDATE, Asset, StaticAssets, asset_response

router = APIRouter(include_in_schema=False)


def _assets(request: Request) -> StaticAssets:
    return request.app.state.probegrid_assets


def _page(request: Request, key: str) -> Asset:
    """A page built once per app and kept on its state."""
    pages: dict[str, Asset] = request.app.state.probegrid_pages
    page = pages.get(key)
    if page is None:
        assets = _assets(request)
        s = assets.prefix
        title = request.app.title
        openapi = request.app.openapi_url or "/openapi.json"
        if key == "index":
            page = assets.page("index.html")
        elif key == "docs":
            html = get_swagger_ui_html(
                openapi_url=openapi, title=f"{title} - Swagger UI",
                swagger_js_url=f"{s}/vendor/swagger-ui-dist/swagger-ui-bundle.js",
                swagger_css_url=f"{s}/vendor/swagger-ui-dist/swagger-ui.css",
                swagger_favicon_url=f"{s}/vendor/swagger-ui-dist/favicon-32x32.png",
                swagger_ui_parameters={"validatorUrl": None},
            )
            page = Asset.of(bytes(html.body), "text/html; charset=utf-8")
        else:
            html = get_redoc_html(
                openapi_url=openapi, title=f"{title} - ReDoc",
                redoc_js_url=f"{s}/vendor/redoc/bundles/redoc.standalone.js",
                redoc_favicon_url=f"{s}/vendor/swagger-ui-dist/favicon-32x32.png",
                with_google_fonts=False,
            )
            page = Asset.of(bytes(html.body), "text/html; charset=utf-8")
        pages[key] = page
    return page


@router.get("/")
async def viewer(request: Request) -> Response:
    """The viewer (a single page; plain ES modules through an import map, no build step)."""
    return asset_response(request, _page(request, "index"), REVALIDATE)


@router.get("/docs")
async def swagger_ui(request: Request) -> Response:
    return asset_response(request, _page(request, "docs"), REVALIDATE)


#: ReDoc's bundle shows a logo from its CDN in the menu (hard-coded, hidden when it fails to
#: load); the page's policy keeps images local so that nothing leaves the machine.
REDOC_POLICY = "img-src 'self' data:"


@router.get("/redoc")
async def redoc(request: Request) -> Response:
    response = asset_response(request, _page(request, "redoc"), REVALIDATE)
    response.headers["Content-Security-Policy"] = REDOC_POLICY
    return response


@router.get("/static/{tag}/{path:path}")
async def static_file(request: Request, tag: str, path: str) -> Response:
    """A packaged file; ``tag`` must be this build's (older URLs are 404, never stale files)."""
    assets = _assets(request)
    asset = assets.get(path) if tag == assets.tag else None
    if asset is None:
        raise ApiError(404, f"There is no static file {path[:128]!r} in this build; reload /.")
    if asset.compressible and not asset.has_gzip:  # compressed once, off the event loop
        await run_in_threadpool(asset.gzipped)
    return asset_response(request, asset, IMMUTABLE)
