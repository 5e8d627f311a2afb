"""GET /viewer: one page, served by the API itself, that segments a dropped or picked .npy cube (or one of
``/v1/examples``) and draws the RA/RD views with the predicted masks, the objects and the compute figures.

The page's HTML, CSS and JavaScript ship in the package (``service/viewer/``); it loads nothing from
elsewhere (the Content-Security-Policy says so to the browser) and talks only to this API's documented
routes: ``/v1/models``, ``/v1/examples`` and ``POST /v1/segment?outputs=objects,masks,views&encoding=zlib``.
"""

from __future__ import annotations

from importlib.resources import files

from fastapi import APIRouter
from fastapi.responses import HTMLResponse, Response

from service.http.errors import ApiError

router = APIRouter(tags=["viewer"])

ASSETS = {"viewer.js": "text/javascript; charset=utf-8", "viewer.css": "text/css; charset=utf-8"}
# Same origin only; data: for ?cube=data:... (a cube given in the address) and the canvases' own images.
HEADERS = {
    "Content-Security-Policy": "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
                               "connect-src 'self' data:; base-uri 'none'; form-action 'none'; "
                               "frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-cache",
}


def _asset(name: str) -> bytes:
    return files("service").joinpath("viewer", name).read_bytes()


@router.get("/viewer", response_class=HTMLResponse, summary="The viewer page")
def viewer_page() -> HTMLResponse:
    """An HTML page: drop or pick a `.npy` cube (complex RAD or log power), an ADC frame (`.npy`) or a DCA1000
    capture (`.bin`, a frame chosen by index; read with the model's radar profile), choose a model and see the RA and RD
    views with the predicted masks, the objects (hover a row to find it on both views), MACs and latency per
    stage and the tenant's usage. `?example=N` segments example N on open, `?model=NAME` chooses the model,
    `?cube=URL` fetches a cube from this origin (or a `data:` URL) and segments it (a capture's frame K with
    `&frame=K`). An API key, when the service
    asks for one, is typed into the page and kept there only (never stored)."""
    return HTMLResponse(_asset("index.html"), headers=HEADERS)


@router.get("/viewer/{name}", include_in_schema=False)
def viewer_asset(name: str) -> Response:
    if name not in ASSETS:
        raise ApiError(404, f"no viewer file {name!r}; the viewer serves {sorted(ASSETS)}")
    return Response(_asset(name), media_type=ASSETS[name], headers=HEADERS)
