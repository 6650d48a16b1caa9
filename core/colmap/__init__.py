"""COLMAP sparse models: the project's own small dataclasses, read/written through pycolmap.

Public API (see :mod:`.model` for the dataclasses):

- ``read_model(path) -> ColmapModel``: text or binary model folder (or a scene folder
  holding ``sparse/0``), validated with clear :class:`~esgs.core.errors.DatasetError`\\ s.
- ``write_model(model, path, binary=True)``: atomically.
"""
from .model import Camera, ColmapModel, Image, Point3D

__all__ = ["Camera", "ColmapModel", "Image", "Point3D"]
