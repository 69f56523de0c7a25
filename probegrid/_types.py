"""Every option set of the library, defined once as a ``Literal``.

Settings models, function signatures, the CLI's argparse ``choices`` (through
:func:`typing.get_args`) and the service's schemas all use these, so a new choice is added in one
place. :func:`choices` gives the tuple of values of one of them.
"""

from __future__ import annotations

from typing import Any, Literal, get_args

__all__ = [
    "CrossLayout",
    "CubeConvention",
    "CubeLayout",
    "DiffuseMethod",
    "EngineTarget",
    "GGXMethod",
    "ImageFormat",
    "InputLayout",
    "Layout",
    "MapDType",
    "MapFormat",
    "MapKind",
    "MapMethod",
    "PixelType",
    "SHKind",
    "SHSource",
    "SHWindow",
    "SeamMode",
    "StartMethod",
    "TraceQuality",
    "VkFormatName",
    "WindowKind",
    "Wrap",
    "choices",
]

#: Cube-map kinds a probe or a store holds: diffuse (irradiance / pi), the GGX specular chain, the
#: unfiltered incoming light.
MapKind = Literal["diffuse", "specular", "incoming"]
#: How a map at a point is made: ``trace`` renders a probe at the point against the converged
#: grid (what a probe baked there holds); ``blend`` mixes the surrounding probes' maps.
MapMethod = Literal["trace", "blend"]
#: The preset of a traced map (:data:`probegrid.bake.point.POINT_PRESETS`): ``accurate`` (the
#: surface cache's indirect light, direct light sampled at every hit), ``fast`` (the cache's
#: direct light too) or ``reference`` (the bake's own gather at every hit).
TraceQuality = Literal["accurate", "fast", "reference"]
#: Number type of a store's map arrays (diffuse, specular, incoming): float32 or float16.
MapDType = Literal["float", "half"]
#: Image layouts of an environment or a cube map (see :mod:`probegrid.core.layouts`).
Layout = Literal["equirect", "angular", "hcross", "vcross", "faces"]
#: An input's layout, or ``auto`` to detect it from the image's shape.
InputLayout = Literal["auto", "equirect", "angular", "hcross", "vcross", "faces"]
#: The two cross layouts.
CrossLayout = Literal["hcross", "vcross"]
#: Layouts cube maps are written in.
CubeLayout = Literal["faces", "hcross", "vcross", "equirect"]
#: HDR image file formats maps are written in.
ImageFormat = Literal["exr", "hdr"]
#: File formats a filtered environment's maps are written in (ktx2: one cube-map file each;
#: gltf: a glTF file with EXT_lights_image_based, RGBD PNG faces, as Babylon.js reads it).
MapFormat = Literal["exr", "hdr", "ktx2", "gltf", "filament"]
#: Whose cube-map lookup a written cube map is arranged for: glTF/OpenGL/KTX2's face table (the
#: store's), three.js' (x mirrored) or Bevy's (z mirrored).
CubeConvention = Literal["gltf", "threejs", "bevy"]
#: Engines a probe grid is exported for (``probegrid export --target``).
EngineTarget = Literal["threejs", "bevy", "ktx2", "filament"]
#: Which SH a query returns: deringed per probe (irradiance never negative) or as stored.
SHKind = Literal["deringed", "raw"]
#: What an SH query interpolates: the store's SH field (a finer lattice reaching the walls,
#: where the store has one) or the probes.
SHSource = Literal["field", "probes"]
#: KTX2 texel formats probegrid writes (Vulkan names without ``VK_FORMAT_``).
VkFormatName = Literal["R16G16B16A16_SFLOAT", "R32G32B32A32_SFLOAT", "E5B9G9R9_UFLOAT_PACK32"]
#: Pixel types of written image files.
PixelType = Literal["half", "float", "rgbe", "uint8"]
#: Seam handling of filtered cube maps (see :mod:`probegrid.core.seams`).
SeamMode = Literal["none", "average", "border"]
#: SH windows (ringing suppression); ``auto`` picks the weakest window that removes negatives.
SHWindow = Literal["none", "hanning", "lanczos", "gauss", "auto"]
#: The explicit SH windows.
WindowKind = Literal["none", "hanning", "lanczos", "gauss"]
#: Diffuse (irradiance / pi) methods: band-2 SH, or the exact cosine sum.
DiffuseMethod = Literal["sh", "exact"]
#: GGX prefilter methods (see :mod:`probegrid.core.specular`).
GGXMethod = Literal["tiered", "fis", "exact"]
#: Start methods of the local worker processes.
StartMethod = Literal["forkserver", "spawn"]
#: glTF texture wrap modes.
Wrap = Literal["repeat", "clamp", "mirror"]


def choices(option: Any) -> tuple[str, ...]:
    """The values of one of this module's ``Literal`` option sets, in order."""
    return tuple(get_args(option))
