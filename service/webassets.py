"""The files of the browser pages (viewer at ``/``, API docs), served from inside the package.

Everything under ``service/static/`` is read once when the app is built (a few MB: the viewer's
own files and the vendored three.js, Swagger UI and ReDoc, see ``scripts/vendor_web.py``). The
files are served at ``/static/<tag>/<path>``, where ``<tag>`` is a digest of every file's content:
a new version of any file changes every URL, so the files can be cached for good
(``Cache-Control: public, max-age=31536000, immutable``), while the pages that name them (``/``,
``/docs``, ``/redoc``) are revalidated on every load (``no-cache`` with an ETag).

A request path is only ever a key of the table built here from the package's own directory; it
never becomes a file path. Text files are sent gzip-compressed (``Content-Encoding: gzip``, made
once on first request, deterministic: no timestamp) to clients that accept it, with
``Vary: Accept-Encoding``; every response carries a strong ETag and answers ``If-None-Match``
with ``304``.
"""

from __future__ import annotations

import gzip
import hashlib
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

from fastapi import Request, Response

__all__ = ["STATIC_DIR", "Asset", "StaticAssets", "asset_response"]

STATIC_DIR: Final = Path(__file__).resolve().parent / "static"
IMMUTABLE: Final = "public, max-age=31536000, immutable"
REVALIDATE: Final = "no-cache"

_MEDIA: Final = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".json": "application/json",
    ".png": "image/png",
    ".md": "text/plain; charset=utf-8",
}
_COMPRESSIBLE: Final = ("text/", "application/json")
#: Bodies smaller than this are sent as they are (gzip would save too little).
MIN_GZIP_BYTES: Final = 1024


def _etag(data: bytes, suffix: str = "") -> str:
    return '"' + hashlib.sha256(data).hexdigest()[:32] + suffix + '"'


def _matches(if_none_match: str | None, etag: str) -> bool:
    if if_none_match is None:
        return False
    tags = (t.strip() for t in if_none_match.split(","))
    return any(t == "*" or t.removeprefix("W/") == etag for t in tags)


def _accepts_gzip(request: Request) -> bool:
    for part in request.headers.get("accept-encoding", "").split(","):
        coding, _, params = part.strip().partition(";")
        if coding.strip().lower() in ("gzip", "*"):
            q = params.strip().removeprefix("q=") if params.strip().startswith("q=") else "1"
            try:
                return float(q) > 0
            except ValueError:
                return False
    return False


@dataclass(eq=False)
class Asset:
    """One file to serve: body, media type, ETag, and its gzip variant (made on first use)."""

    body: bytes
    media_type: str
    etag: str
    _gzip: tuple[bytes, str] | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @classmethod
    def of(cls, body: bytes, media_type: str) -> Asset:
        return cls(body=body, media_type=media_type, etag=_etag(body))

    @property
    def compressible(self) -> bool:
        return self.media_type.startswith(_COMPRESSIBLE) and len(self.body) >= MIN_GZIP_BYTES

    @property
    def has_gzip(self) -> bool:
        return self._gzip is not None

    def gzipped(self) -> tuple[bytes, str]:
        """The gzip body (level 6, mtime 0: the same bytes every time) and its ETag.

        Level 6 rather than 9: 0.6 % larger for three.js and a third faster to make on the
        first request (measured)."""
        if self._gzip is None:
            with self._lock:
                if self._gzip is None:
                    z = gzip.compress(self.body, compresslevel=6, mtime=0)
                    self._gzip = (z, _etag(self.body, "-gz"))
        return self._gzip


def asset_response(request: Request, asset: Asset, cache_control: str) -> Response:
    """The asset (gzip-encoded when the client accepts it), or 304 when its ETag matches."""
    body, etag = asset.body, asset.etag
    headers = {"Cache-Control": cache_control}
    if asset.compressible:
        headers["Vary"] = "Accept-Encoding"
        if _accepts_gzip(request):
            body, etag = asset.gzipped()
            headers["Content-Encoding"] = "gzip"
    headers["ETag"] = etag
    if _matches(request.headers.get("if-none-match"), etag):
        headers.pop("Content-Encoding", None)
        return Response(status_code=304, headers=headers)
    return Response(content=body, media_type=asset.media_type, headers=headers)


class StaticAssets:
    """The files under :data:`STATIC_DIR`, keyed by their path relative to it."""

    def __init__(self, root: Path = STATIC_DIR) -> None:
        files: dict[str, Asset] = {}
        digest = hashlib.sha256()
        for f in sorted(p for p in root.rglob("*") if p.is_file()):
            rel = f.relative_to(root).as_posix()
            if "__pycache__" in rel:
                continue
            body = f.read_bytes()
            media = _MEDIA.get(f.suffix.lower(), "text/plain; charset=utf-8")
            files[rel] = Asset.of(body, media)
            digest.update(rel.encode() + b"\0" + files[rel].etag.encode() + b"\0")
        self.files = files
        #: Content digest of every file: the URL prefix ``/static/<tag>/``.
        self.tag = digest.hexdigest()[:16]
        self.prefix = f"/static/{self.tag}"

    def get(self, path: str) -> Asset | None:
        return self.files.get(path)

    def page(self, name: str) -> Asset:
        """An HTML page with ``{{STATIC}}`` replaced by this build's static URL prefix."""
        text = self.files[name].body.decode("utf-8").replace("{{STATIC}}", self.prefix)
        return Asset.of(text.encode("utf-8"), _MEDIA[".html"])
