"""The surgeon's display and the API docs, served by the daemon with every asset from the package (no CDN).

``/`` the display page (read-only: looking needs no token), ``/display/assets/*``
its script and style, ``/ws`` the live WebSocket, ``/display/ct.json`` and
``/display/ct.bin`` the CT for video-CT mode (sent once, resliced in the
browser), ``/docs`` and ``/redoc`` with Swagger UI and ReDoc from the
``fastapi-offline`` package's files, so they render on an air-gapped network.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
from importlib import resources
from pathlib import Path

from fastapi import APIRouter, FastAPI, HTTPException, WebSocket, WebSocketDisconnect
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, Response

from .display_hub import DisplayHub

__all__ = ["display_router", "docs_router", "STATIC_DIR"]

STATIC_DIR = Path(__file__).with_name("display_static")
_ASSETS = {"display.js": "text/javascript", "display.css": "text/css"}
_DOC_ASSETS = {"swagger-ui-bundle.js": "text/javascript", "swagger-ui.css": "text/css", "redoc.standalone.js": "text/javascript", "favicon.png": "image/png"}
# No caching, so a daemon upgrade is never shown with an old script; and a Content-Security-Policy that lets the
# page reach its own host only (an air-gapped OR network: nothing else may be asked for, not even a logo).
_CSP = "default-src 'self'; img-src 'self' data: blob:; style-src 'self' 'unsafe-inline'; script-src 'self' 'unsafe-inline'; worker-src 'self' blob:; connect-src 'self'"
_NO_STORE = {"Cache-Control": "no-store", "Content-Security-Policy": _CSP}


def display_router(hub: DisplayHub | None) -> APIRouter:
    """The page and its assets always; the live socket and the CT only with a hub (a daemon, not a bare API)."""
    router = APIRouter(include_in_schema=False)

    @router.get("/")
    def page() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", media_type="text/html", headers=_NO_STORE)

    @router.get("/favicon.ico")
    def favicon() -> FileResponse:
        return FileResponse(_doc_asset_path("favicon.png"), media_type="image/png")

    @router.get("/display/assets/{name}")
    def asset(name: str) -> FileResponse:
        if name not in _ASSETS:  # a fixed list: no path from the request ever reaches the file system
            raise HTTPException(404, f"no display asset '{name}'")
        return FileResponse(STATIC_DIR / name, media_type=_ASSETS[name], headers=_NO_STORE)

    @router.get("/display/ct.json")
    def ct_meta() -> dict:
        vol = hub.ct_volume() if hub is not None else None
        if vol is None:
            raise HTTPException(404, "no CT: the daemon runs without video-CT mode")
        return vol.meta()

    @router.get("/display/ct.bin")
    def ct_bin() -> Response:
        vol = hub.ct_volume() if hub is not None else None
        if vol is None:
            raise HTTPException(404, "no CT: the daemon runs without video-CT mode")
        return Response(vol.data, media_type="application/octet-stream")

    @router.websocket("/ws")
    async def live(ws: WebSocket) -> None:
        await ws.accept()
        if hub is None:
            await ws.close(code=1011, reason="no live streams in this server")
            return
        client = hub.attach()
        try:
            # The socket is send-only; a reader notices the browser leaving while the sender waits for news.
            reader = asyncio.ensure_future(_drain(ws))
            while not reader.done():
                batch = asyncio.ensure_future(client.next_batch())
                done, _ = await asyncio.wait({batch, reader}, return_when=asyncio.FIRST_COMPLETED)
                if batch not in done:
                    batch.cancel()
                    break
                for text in batch.result():
                    await ws.send_text(text)
        except (WebSocketDisconnect, RuntimeError):
            pass  # the browser went away mid-send
        finally:
            hub.detach(client)
            reader.cancel()
            with contextlib.suppress(RuntimeError, WebSocketDisconnect):  # closed already, from either side
                await ws.close()

    return router


async def _drain(ws: WebSocket) -> None:
    with contextlib.suppress(WebSocketDisconnect, RuntimeError):
        while True:
            await ws.receive_text()


def _doc_asset_path(name: str) -> Path:
    return Path(str(resources.files("fastapi_offline") / "static" / name))


# ReDoc's bundle names one file on its makers' server, the logo of its "API docs by Redocly" footer; served with
# that address turned into the packaged icon, the page asks nothing of the internet (the CSP would only block it).
_REWRITES = {"redoc.standalone.js": [(b"https://cdn.redoc.ly/redoc/logo-mini.svg", b"/docs/assets/favicon.png")]}


@functools.cache
def _doc_asset(name: str) -> bytes:
    data = _doc_asset_path(name).read_bytes()
    for old, new in _REWRITES.get(name, []):
        if old not in data:
            raise RuntimeError(f"{name} from fastapi-offline no longer holds {old.decode()}: check it for other outside addresses")
        data = data.replace(old, new)
    return data


def docs_router(app: FastAPI) -> APIRouter:
    """``/docs`` and ``/redoc`` from packaged files; ``create_app`` must pass ``docs_url=None, redoc_url=None``."""
    router = APIRouter(include_in_schema=False)

    @router.get("/docs")
    def swagger() -> HTMLResponse:
        page = get_swagger_ui_html(openapi_url=app.openapi_url or "/openapi.json", title=f"{app.title} - API", swagger_js_url="/docs/assets/swagger-ui-bundle.js",
                                   swagger_css_url="/docs/assets/swagger-ui.css", swagger_favicon_url="/docs/assets/favicon.png")
        page.headers.update(_NO_STORE)
        return page

    @router.get("/redoc")
    def redoc() -> HTMLResponse:
        # with_google_fonts=False: ReDoc's default pulls fonts from the internet.
        # The CSP also keeps ReDoc's "powered by" logo, an image on its makers' server, from being asked for.
        page = get_redoc_html(openapi_url=app.openapi_url or "/openapi.json", title=f"{app.title} - ReDoc", redoc_js_url="/docs/assets/redoc.standalone.js",
                              redoc_favicon_url="/docs/assets/favicon.png", with_google_fonts=False)
        page.headers.update(_NO_STORE)
        return page

    @router.get("/docs/assets/{name}")
    def doc_asset(name: str) -> Response:
        if name not in _DOC_ASSETS:
            raise HTTPException(404, f"no docs asset '{name}'")
        return Response(_doc_asset(name), media_type=_DOC_ASSETS[name])

    return router
