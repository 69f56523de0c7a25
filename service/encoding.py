"""Response bodies of the map routes, and strong ETags.

Cube formats
------------
``format`` x ``layout`` of a ``(6, n, n, 3)`` float32 cube:

========  =========================================  ===========================================
format    ``layout=faces``                           ``layout=cross``
========  =========================================  ===========================================
npy       ``(6, n, n, 3)`` float32 ``.npy``          ``(3n, 4n, 3)`` float32 horizontal cross
json      ``{"shape", "data"}``, data nested lists   the same for the cross image
          (non-finite values as ``null``)
exr       float32 RGB OpenEXR of the six faces       float32 RGB OpenEXR of the cross
          stacked top to bottom (``6n x n``)
hdr       Radiance RGBE, same images                 Radiance RGBE of the cross
ktx2      KTX 2.0 cube map, one level,               KTX 2.0 2D texture of the cross, same
          R32G32B32A32_SFLOAT (alpha 1)              format (row 0 at the top)
png       8-bit sRGB (linear values clamped to       8-bit sRGB of the cross
          [0, 1], sRGB transfer curve), same images
========  =========================================  ===========================================

Faces are in the order ``+X, -X, +Y, -Y, +Z, -Z`` with row 0 at the top (:mod:`probegrid.core.cubemap`);
the cross is :func:`probegrid.core.layouts.faces_to_cross` ``"hcross"`` (uncovered cells 0). The exr,
hdr and png encoders are :func:`probegrid.imageio.write_image`, which writes files: each image is
written to a fresh file in the service's scratch directory (in ``/dev/shm`` when it exists, so it
never touches a disk), read back and deleted; a write that fails (a full scratch file system) is
a ``503 scratch_unavailable`` with ``Retry-After``, never an empty body. Every encoder is
deterministic (EXRs carry no capture date), so the same query always returns the same bytes.

ETags
-----
A strong ETag is the quoted hex digest of the body's SHA-256, truncated to 128 bits (SHA-256
rather than BLAKE2b because OpenSSL's runs on the CPU's SHA instructions: 11 us for a 16^2 npy
cube against 20 us, measured). ``If-None-Match`` is compared with the weak comparison of
RFC 9110 section 13.1.2 (``W/`` prefixes ignored, ``*`` matches), and a match answers
``304 Not Modified`` with the ETag and no body.
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
import secrets
import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Final

import numpy as np
from fastapi import Request, Response
from numpy.typing import NDArray
from pydantic_core import to_json

from probegrid.core.layouts import faces_to_cross
from probegrid.export.ktx2 import VK_FORMAT_R32G32B32A32_SFLOAT, encode_ktx2
from probegrid.errors import ImageError
from probegrid.imageio import write_image
from service.errors import ApiError

__all__ = [
    "MEDIA_TYPES",
    "conditional_response",
    "cube_image",
    "encode_cube",
    "etag_of",
    "scratch_directory",
]

MEDIA_TYPES: Final[dict[str, str]] = {
    "exr": "image/x-exr",
    "hdr": "image/vnd.radiance",
    "png": "image/png",
    "npy": "application/x-npy",
    "json": "application/json",
    "ktx2": "image/ktx2",
}
CACHE_CONTROL: Final = "no-cache"
_log = logging.getLogger("probegrid.service")


def etag_of(body: bytes) -> str:
    """Strong ETag of a body: ``"<first 128 bits of its SHA-256, hex>"``."""
    return '"' + hashlib.sha256(body).hexdigest()[:32] + '"'


def _matches(if_none_match: str, etag: str) -> bool:
    tags = (t.strip() for t in if_none_match.split(","))
    return any(t == "*" or t.removeprefix("W/") == etag for t in tags)


def conditional_response(
    request: Request, body: bytes, media_type: str, headers: dict[str, str] | None = None
) -> Response:
    """``200`` with ``body`` and its strong ETag, or ``304`` if ``If-None-Match`` matches it."""
    etag = etag_of(body)
    h = {"ETag": etag, "Cache-Control": CACHE_CONTROL}
    inm = request.headers.get("if-none-match")
    if inm is not None and _matches(inm, etag):
        return Response(status_code=304, headers=h)
    if headers:
        h.update(headers)
    return Response(content=body, media_type=media_type, headers=h)


def scratch_directory() -> Path:
    """A new private directory for image encoding (under /dev/shm when available); the caller
    removes it."""
    shm = Path("/dev/shm")
    base = str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None
    return Path(tempfile.mkdtemp(prefix="probegrid-service-", dir=base))


@lru_cache(maxsize=64)
def _npy_header(shape: tuple[int, ...]) -> bytes:
    """The ``.npy`` (format 1.0) header ``np.save`` writes for a C-ordered float32 array."""
    buf = io.BytesIO()
    header = {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float32)),
              "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue()


def cube_image(faces: NDArray[np.float32], layout: str) -> NDArray[np.float32]:
    """The array a layout serves: ``(6, n, n, 3)`` faces or the ``(3n, 4n, 3)`` cross."""
    return faces if layout == "faces" else faces_to_cross(faces, "hcross")


#: EXR header attributes of every served EXR: OpenImageIO stamps the current time as the
#: ``capDate`` attribute unless ``DateTime`` is given, and an empty one leaves it out, so the
#: same query gives the same bytes at any time.
_EXR_METADATA: Final = {"DateTime": ""}


#: Seconds a client is asked to wait after a failed image encoding (``Retry-After``).
SCRATCH_RETRY_AFTER: Final = 5


def _encode_image(image: NDArray[np.float32], fmt: str, scratch: Path) -> bytes:
    """The image encoded through a scratch file; a write that fails (a full scratch file
    system, say) is a 503 with a generic message (the cause is logged, the path is not sent)."""
    path = scratch / f"{secrets.token_hex(12)}.{fmt}"
    try:
        write_image(path, image, half=False, metadata=_EXR_METADATA)
        body = path.read_bytes()
        if not body:
            raise ImageError(f"{path}: the encoded image is empty.")
        return body
    except (ImageError, OSError) as exc:
        _log.error("cannot encode a %s image in %s: %s", fmt, scratch, exc)
        raise ApiError(503, "The server cannot encode images right now; try again later.",
                       code="scratch_unavailable",
                       headers={"Retry-After": str(SCRATCH_RETRY_AFTER)}) from None
    finally:
        path.unlink(missing_ok=True)


def encode_cube(
    faces: NDArray[np.float32],
    *,
    fmt: str,
    layout: str,
    scratch: Path,
    meta: dict[str, object] | None = None,
) -> bytes:
    """Encode a ``(6, n, n, 3)`` cube in one of :data:`MEDIA_TYPES`' formats (module docstring).

    ``meta`` is merged into the JSON document (ignored by the other formats).
    """
    if fmt not in MEDIA_TYPES:
        raise ValueError(f"unknown format {fmt!r}; choose one of {', '.join(MEDIA_TYPES)}.")
    if layout not in ("faces", "cross", "hcross"):  # hcross: the CLI's name of the cross
        raise ValueError(f"unknown layout {layout!r}; choose 'faces' or 'hcross' ('cross').")
    arr = np.ascontiguousarray(cube_image(faces, layout), dtype=np.float32)
    if fmt == "npy":  # exactly np.save's bytes (tested), without its per-call header building
        return _npy_header(arr.shape) + arr.tobytes()
    if fmt == "ktx2":  # a KTX2 cube (OpenGL/KTX2 face table), or the cross as a 2D texture,
        # float32 like the EXR
        return encode_ktx2([arr], kind="cube" if layout == "faces" else "2d",
                           vk_format=VK_FORMAT_R32G32B32A32_SFLOAT,
                           key_values={"probegrid:meta": to_json(meta or {}).decode()})
    if fmt == "json":
        doc = dict(meta or {})
        doc.update(layout=layout, shape=list(arr.shape), data=arr.tolist())
        return to_json(doc, inf_nan_mode="null")
    image = arr if layout != "faces" else arr.reshape(-1, arr.shape[2], arr.shape[3])
    return _encode_image(image, fmt, scratch)
