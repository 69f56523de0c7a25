"""Scenes: the triangle model with materials and lights, textures, builders and the glTF loader.

``model`` (:class:`Scene`, :class:`Material`, :class:`Surface`), ``textures`` (glTF sampler
lookups), ``builders`` (quads, boxes, :class:`SceneBuilder`) and ``gltf`` (:func:`load_gltf`, the
one module that imports trimesh).
"""

from probegrid.errors import SceneError
from probegrid.scene.builders import SceneBuilder, box_mesh, box_scene, quad_mesh
from probegrid.scene.gltf import load_gltf
from probegrid.scene.model import Material, Scene, Surface
from probegrid.scene.textures import TexCoord, Wrap, sample_texture, texture_transform

__all__ = [
    "Material",
    "Scene",
    "SceneBuilder",
    "SceneError",
    "Surface",
    "TexCoord",
    "Wrap",
    "box_mesh",
    "box_scene",
    "load_gltf",
    "quad_mesh",
    "sample_texture",
    "texture_transform",
]
