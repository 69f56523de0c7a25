"""glTF geometry made plain before the mesh reader sees it: compressed, quantized and sparse
accessors decoded into float32 positions and texture coordinates and uint32 indices.

:func:`plain_geometry` rewrites a glTF document (its JSON and its buffers' bytes) so that every
accessor a triangle primitive reads (``POSITION``, ``TEXCOORD_n``, ``COLOR_0``, ``indices``)
is a plain, dense array in a buffer, as any glTF reader reads it:

* ``EXT_meshopt_compression`` -- each compressed buffer view is decoded (meshoptimizer, the
  package's ``meshopt`` extra:
  its ``decode_vertex_buffer`` / ``decode_index_buffer`` / ``decode_index_sequence`` for the
  modes ATTRIBUTES / TRIANGLES / INDICES, then the OCTAHEDRAL, QUATERNION or EXPONENTIAL
  filter) into the bytes the view describes; the fallback buffers (often without data) are
  never read;
* ``KHR_draco_mesh_compression`` -- the primitive's Draco blob is decoded (DracoPy) into its
  attributes and faces, by the extension's attribute ids;
* ``KHR_mesh_quantization`` and the core spec's normalized integers -- integer positions and
  texture coordinates become float32: ``normalized`` ones by glTF's rule (``c / 255`` for
  unsigned bytes, ``max(c / 127, -1)`` for signed ones, likewise for shorts), the others as
  their integer values (a node's scale then places them);
* sparse accessors -- the base (a buffer view or zeros) with the sparse values written at the
  sparse indices (glTF 2.0, 3.6.2.3).

A document with none of these is returned untouched (the same bytes reach the reader). The
decoded data land in one new buffer; accessors that change point at it.

Reference: glTF 2.0 specification, 3.6 "Buffers, buffer views and accessors";
KHR_mesh_quantization, EXT_meshopt_compression and KHR_draco_mesh_compression specifications.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Final

import numpy as np
from numpy.typing import NDArray

from probegrid.errors import SceneError

__all__ = ["DECODED_URI", "float_accessor", "plain_geometry", "read_accessor", "view_bytes"]

#: The URI under which the decoded data are handed to the mesh reader.
DECODED_URI: Final[str] = "probegrid-decoded.bin"

#: glTF component types -> numpy little-endian dtypes.
_DTYPES: Final[dict[int, str]] = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2",
                                   5125: "<u4", 5126: "<f4"}

#: Components per element of the accessor types.
_WIDTH: Final[dict[str, int]] = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4,
                                 "MAT3": 9, "MAT4": 16}

#: Largest decoded accessor or buffer view (bytes): a count a file declares is not trusted.
MAX_DECODED_BYTES: Final[int] = 1 << 31

_MESHOPT: Final[str] = "EXT_meshopt_compression"
_DRACO: Final[str] = "KHR_draco_mesh_compression"


def view_bytes(header: dict, buffers: Sequence[bytes], i: int, label: str) -> bytes:
    """The bytes of buffer view ``i`` (decoded first when meshopt-compressed)."""
    view = header["bufferViews"][i]
    ext = view.get("extensions", {}).get(_MESHOPT)
    if ext is not None:
        return _meshopt_view(ext, buffers, i, label)
    buf = buffers[int(view["buffer"])]
    start = int(view.get("byteOffset", 0))
    end = start + int(view["byteLength"])
    if not 0 <= start <= end <= len(buf):
        raise SceneError(f"{label}: buffer view {i} runs past the end of its buffer.")
    return buf[start:end]


def _meshopt_view(ext: dict, buffers: Sequence[bytes], i: int, label: str) -> bytes:
    """An ``EXT_meshopt_compression`` buffer view, decoded (module docstring)."""
    try:
        import meshoptimizer
    except ImportError:  # pragma: no cover -- the `meshopt` extra
        raise SceneError(f"{label}: buffer view {i} is EXT_meshopt_compression-compressed and "
                         "the meshoptimizer package is missing: pip install 'probegrid[meshopt]'."
                         ) from None
    buf = buffers[int(ext["buffer"])]
    start = int(ext.get("byteOffset", 0))
    data = buf[start:start + int(ext["byteLength"])]
    count, stride = int(ext["count"]), int(ext["byteStride"])
    mode, filt = ext.get("mode", "ATTRIBUTES"), ext.get("filter", "NONE")
    if count < 0 or stride < 1 or count * stride > MAX_DECODED_BYTES:
        raise SceneError(f"{label}: buffer view {i} declares {count} x {stride} bytes.")
    try:
        if mode == "ATTRIBUTES":
            # (returned as float32 rows of ``stride`` bytes: the bytes are what counts)
            out = np.asarray(meshoptimizer.decode_vertex_buffer(count, stride, data))
            if filt != "NONE":
                decode = {"OCTAHEDRAL": meshoptimizer.decode_filter_oct,
                          "QUATERNION": meshoptimizer.decode_filter_quat,
                          "EXPONENTIAL": meshoptimizer.decode_filter_exp}[filt]
                out = np.asarray(decode(out, count, stride))
        elif mode == "TRIANGLES":
            out = np.asarray(meshoptimizer.decode_index_buffer(count, stride, data))
        elif mode == "INDICES":
            out = np.asarray(meshoptimizer.decode_index_sequence(count, stride, data))
        else:
            raise SceneError(f"{label}: buffer view {i} has meshopt mode {mode!r}.")
    except SceneError:
        raise
    except (KeyError, ValueError, RuntimeError, TypeError) as exc:
        raise SceneError(f"{label}: buffer view {i} could not be meshopt-decoded "
                         f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})."
                         ) from None
    if mode != "ATTRIBUTES":  # the decoders return integers of the index size
        out = out.astype(f"<u{stride}")
    raw = np.ascontiguousarray(out).tobytes()
    if len(raw) != count * stride:
        raise SceneError(f"{label}: buffer view {i} decoded to {len(raw)} bytes, expected "
                         f"{count * stride}.")
    return raw


def read_accessor(header: dict, buffers: Sequence[bytes], index: int, label: str
                  ) -> NDArray:
    """Accessor ``index`` as stored: ``(count, width)`` of its component type, strides,
    offsets and sparse substitution applied (no normalization)."""
    acc = header["accessors"][index]
    dtype = np.dtype(_DTYPES[int(acc["componentType"])])
    width = _WIDTH[acc["type"]]
    count = int(acc["count"])
    item = dtype.itemsize * width
    if count < 0 or count * item > MAX_DECODED_BYTES:
        raise SceneError(f"{label}: accessor {index} declares {count} elements.")
    if "bufferView" in acc:
        vi = int(acc["bufferView"])
        data = view_bytes(header, buffers, vi, label)
        stride = int(header["bufferViews"][vi].get("byteStride", 0)) or item
        start = int(acc.get("byteOffset", 0))
        if count and (start < 0 or start + (count - 1) * stride + item > len(data)):
            raise SceneError(f"{label}: accessor {index} runs past the end of its buffer view.")
        raw = np.frombuffer(data, np.uint8, count=max(count - 1, 0) * stride + item
                            if count else 0, offset=start)
        rows = np.lib.stride_tricks.as_strided(raw, (count, item), (stride, 1)) if count \
            else raw.reshape(0, item)
        out = np.ascontiguousarray(rows).view(dtype).reshape(count, width).copy()
    else:
        out = np.zeros((count, width), dtype)
    sparse = acc.get("sparse")
    if sparse:
        k = int(sparse["count"])
        ind, val = sparse["indices"], sparse["values"]
        idt = np.dtype(_DTYPES[int(ind["componentType"])])
        ib = view_bytes(header, buffers, int(ind["bufferView"]), label)
        vb = view_bytes(header, buffers, int(val["bufferView"]), label)
        io, vo = int(ind.get("byteOffset", 0)), int(val.get("byteOffset", 0))
        if io + k * idt.itemsize > len(ib) or vo + k * item > len(vb):
            raise SceneError(f"{label}: the sparse data of accessor {index} run past their "
                             "buffer views.")
        idx = np.frombuffer(ib, idt, count=k, offset=io).astype(np.int64)
        if k and (idx.min() < 0 or idx.max() >= count):
            raise SceneError(f"{label}: accessor {index} has sparse indices out of range.")
        out[idx] = np.frombuffer(vb, dtype, count=k * width, offset=vo).reshape(k, width)
    return out


def float_accessor(header: dict, buffers: Sequence[bytes], index: object, label: str
                   ) -> NDArray[np.float64]:
    """Accessor ``index`` as ``(count, width)`` float64 values (normalized integers by
    glTF's rule, :func:`_as_float`); a :class:`SceneError` for an index that is not one."""
    accs = header.get("accessors", [])
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(accs):
        raise SceneError(f"{label}: {index!r} is not an accessor index.")
    try:
        raw = read_accessor(header, buffers, index, label)
    except (KeyError, ValueError, TypeError) as exc:
        raise SceneError(f"{label}: accessor {index} cannot be read ({exc}).") from None
    return _as_float(raw, bool(accs[index].get("normalized", False))).astype(np.float64)


def _as_float(a: NDArray, normalized: bool) -> NDArray[np.float32]:
    """Integers to float32 by glTF's rules (module docstring); floats as they are."""
    if a.dtype.kind == "f":
        return a.astype(np.float32)
    if not normalized:
        return a.astype(np.float32)
    top = float(np.iinfo(a.dtype).max)
    f = a.astype(np.float64) / top
    return np.maximum(f, -1.0).astype(np.float32)


def _geometry_accessors(prim: dict) -> list[tuple[str, int]]:
    """The (attribute name, accessor) pairs a triangle primitive's reader takes."""
    attrs = prim.get("attributes", {})
    out = [(k, int(v)) for k, v in attrs.items()
           if k == "POSITION" or k == "COLOR_0" or k.startswith("TEXCOORD_")]
    if "indices" in prim:
        out.append(("indices", int(prim["indices"])))
    return out


def _needs_plain(header: dict, index: int, name: str) -> bool:
    acc = header["accessors"][index]
    if acc.get("sparse") or "bufferView" not in acc:
        return True
    view = header["bufferViews"][int(acc["bufferView"])]
    if _MESHOPT in view.get("extensions", {}):
        return True
    ctype = int(acc.get("componentType", 5126))
    if name == "indices":
        return False
    return name != "COLOR_0" and ctype != 5126  # quantized positions or coordinates


def plain_geometry(header: dict, buffers: Sequence[bytes], label: str
                   ) -> tuple[dict, bytes] | None:
    """The document with every geometry accessor plain (module docstring), or None when it
    has none to decode.

    Returns ``(header, decoded)``: a copy of ``header`` whose changed accessors point at a new
    last buffer of URI :data:`DECODED_URI` holding ``decoded``; the meshopt buffer views are
    made plain too (their fallback buffers are never read). Raises :class:`SceneError` for
    data that cannot be decoded.
    """
    draco = []
    todo: dict[int, str] = {}
    for m in header.get("meshes", []):
        for prim in m.get("primitives", []):
            if _DRACO in prim.get("extensions", {}):
                draco.append(prim)
                continue
            for name, acc in _geometry_accessors(prim):
                if _needs_plain(header, acc, name):
                    todo.setdefault(acc, name)
    meshopt_views = [i for i, v in enumerate(header.get("bufferViews", []))
                     if _MESHOPT in v.get("extensions", {})]
    if not draco and not todo and not meshopt_views:
        return None
    out = copy.deepcopy(header)
    chunks: list[bytes] = []
    size = 0
    new_buffer = len(out.get("buffers", []))

    def append(raw: bytes, stride: int | None = None) -> int:
        nonlocal size
        pad = -size % 4
        if pad:
            chunks.append(b"\0" * pad)
            size += pad
        view = {"buffer": new_buffer, "byteOffset": size, "byteLength": len(raw)}
        if stride:
            view["byteStride"] = stride
        out["bufferViews"].append(view)
        chunks.append(raw)
        size += len(raw)
        return len(out["bufferViews"]) - 1

    out.setdefault("bufferViews", [])

    def put(index: int, values: NDArray, name: str) -> None:
        acc = out["accessors"][index]
        if name == "indices":
            arr = np.ascontiguousarray(values, "<u4").reshape(-1)
            acc.update(componentType=5125, type="SCALAR", count=len(arr))
        else:
            arr = np.ascontiguousarray(values, "<f4")
            arr = arr.reshape(len(arr), -1)
            acc.update(componentType=5126, count=len(arr),
                       type={1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4"}[arr.shape[1]])
            acc.pop("min", None)
            acc.pop("max", None)
        acc.pop("sparse", None)
        acc.pop("normalized", None)
        acc["byteOffset"] = 0
        acc["bufferView"] = append(arr.tobytes())

    for index, name in sorted(todo.items()):
        raw = read_accessor(header, buffers, index, label)
        acc = header["accessors"][index]
        if name == "indices":
            put(index, raw, name)
        else:
            put(index, _as_float(raw, bool(acc.get("normalized", False))), name)
    for prim in draco:
        _decode_draco(header, buffers, prim, out, put, label)
    # meshopt views the reader may still read (normals, images...): plain bytes
    for i in meshopt_views:
        view = out["bufferViews"][i]
        raw = view_bytes(header, buffers, i, label)
        j = append(raw, int(view["byteStride"]) if "byteStride" in view else None)
        out["bufferViews"][i] = out["bufferViews"][j]
    out.setdefault("buffers", []).append({"byteLength": size, "uri": DECODED_URI})
    for prim_mesh in out.get("meshes", []):
        for prim in prim_mesh.get("primitives", []):
            prim.get("extensions", {}).pop(_DRACO, None)
    return out, b"".join(chunks)


def _decode_draco(header: dict, buffers: Sequence[bytes], prim: dict, out: dict, put,
                  label: str) -> None:
    """Decode a ``KHR_draco_mesh_compression`` primitive's attributes and faces into plain
    accessors of ``out`` (by :func:`plain_geometry`'s ``put``)."""
    try:
        import DracoPy
    except ImportError:  # pragma: no cover -- a dependency of the package
        raise SceneError(f"{label}: a primitive is Draco-compressed and the DracoPy package is "
                         "missing (pip install DracoPy).") from None
    ext = prim["extensions"][_DRACO]
    blob = view_bytes(header, buffers, int(ext["bufferView"]), label)
    try:
        mesh = DracoPy.decode(blob)
    except Exception as exc:  # noqa: BLE001 -- DracoPy raises its own types
        raise SceneError(f"{label}: a Draco-compressed primitive could not be decoded "
                         f"({type(exc).__name__}).") from None
    by_id = {int(a["unique_id"]): np.asarray(a["data"]) for a in mesh.attributes}
    for name, ident in ext.get("attributes", {}).items():
        if name not in prim.get("attributes", {}):
            continue
        if int(ident) not in by_id:
            raise SceneError(f"{label}: a Draco primitive has no attribute {ident} ({name}).")
        data = by_id[int(ident)]
        if name == "POSITION" or name == "COLOR_0" or name.startswith("TEXCOORD_"):
            acc = header["accessors"][int(prim["attributes"][name])]
            normalized = bool(acc.get("normalized", False)) or (
                name == "COLOR_0" and data.dtype.kind in "ui")
            put(int(prim["attributes"][name]), _as_float(data.reshape(len(data), -1),
                                                        normalized), name)
    faces = getattr(mesh, "faces", None)
    if "indices" in prim and faces is not None:
        put(int(prim["indices"]), np.asarray(faces), "indices")
