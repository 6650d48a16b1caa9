"""Depth/normal label maps of any COLMAP scene, rendered from a mesh (``priors/labels/``).

- :mod:`.fill`: which missing pixels are filled and how (the filled ones are flagged);
- :mod:`.writer`: the atomic ``priors/labels`` writer used by the Blender renderer;
- :mod:`.mesh_io`: label meshes as arrays;
- :mod:`.stereo`, :mod:`.reconstruct`: a mesh rebuilt on the CPU from the scene's images;
- :mod:`.accuracy`: AbsRel / delta1 of labels against ground truth.

The rendering itself needs Blender: :func:`esgs.esgs_addon.render_labels.render_labels`,
run in a child process by ``esgs labels``.
"""
from .fill import FILLED, RENDERED, FillOptions, fill_missing
from .mesh_io import load_mesh, write_mesh
from .writer import LabelWriter

__all__ = ["FILLED", "RENDERED", "FillOptions", "LabelWriter", "fill_missing", "load_mesh", "write_mesh"]
