"""Point-cloud objects from numpy arrays, without per-point Python loops.

Blender 5.0 has no Python call to resize a ``PointCloud``; building a mesh of loose
vertices with ``foreach_set`` and converting it keeps every attribute and is fast
(1M points with 4 attributes: ~0.4 s), so that is what :func:`point_cloud_object` does.
"""
from __future__ import annotations

import bpy
import numpy as np

from ..core.errors import ConfigError

COLOR_ATTRIBUTE = "color"
#: What the point material reads. Cycles reserves the name "color" for volume grids and
#: finds nothing under it on point clouds (renders black), so the 8-bit sRGB colours are
#: also kept, losslessly and at 4 bytes a point, as a byte-colour attribute of this name.
RENDER_COLOR_ATTRIBUTE = "rgb"
MATERIAL_NAME = "ESGS point colour"


def _attribute_spec(values: np.ndarray, count: int, name: str) -> tuple[str, str, np.ndarray]:
    """(Blender data type, foreach field, flat values) for a per-point array."""
    values = np.asarray(values)
    if values.ndim == 2 and values.dtype == np.uint8 and values.shape[1] in (3, 4):
        # 8-bit sRGB colours -> Blender byte colour (stored as sRGB, read back as linear)
        rgba = np.full((values.shape[0], 4), 255, dtype=np.uint8)
        rgba[:, : values.shape[1]] = values
        return "BYTE_COLOR", "color_srgb", (rgba / 255.0).astype(np.float32).reshape(-1)
    if values.shape[0] != count:
        raise ConfigError(f"attribute '{name}' has {values.shape[0]} values for {count} points")
    if values.ndim == 1:
        if values.dtype == np.bool_:
            return "BOOLEAN", "value", values.astype(bool)
        if np.issubdtype(values.dtype, np.integer):
            return "INT", "value", values.astype(np.int32)
        return "FLOAT", "value", values.astype(np.float32)
    if values.ndim == 2 and values.shape[1] == 3:
        return "FLOAT_VECTOR", "vector", values.astype(np.float32).reshape(-1)
    if values.ndim == 2 and values.shape[1] == 4:
        return "FLOAT_COLOR", "color", values.astype(np.float32).reshape(-1)
    raise ConfigError(f"attribute '{name}' has unsupported shape {values.shape}")


def point_color_material(
    name: str = MATERIAL_NAME, attribute_name: str = RENDER_COLOR_ATTRIBUTE
) -> bpy.types.Material:
    """A material showing each point's colour attribute ``attribute_name`` (reused if it exists).

    Do not pass "color": Cycles does not find attributes of that name on point clouds.
    """
    material = bpy.data.materials.get(name)
    if material is not None:
        return material
    material = bpy.data.materials.new(name)
    tree = material.node_tree  # Blender 5.0 materials always have a node tree
    tree.nodes.clear()
    attribute = tree.nodes.new("ShaderNodeAttribute")
    attribute.attribute_type = "GEOMETRY"
    attribute.attribute_name = attribute_name
    attribute.location = (-400, 0)
    # emission: the SfM colour is already the observed (lit) colour, so do not shade it again
    emission = tree.nodes.new("ShaderNodeEmission")
    emission.location = (-150, 0)
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    output.location = (100, 0)
    tree.links.new(attribute.outputs["Color"], emission.inputs["Color"])
    tree.links.new(emission.outputs["Emission"], output.inputs["Surface"])
    return material


def point_cloud_object(
    name: str,
    positions: np.ndarray,
    attributes: dict[str, np.ndarray] | None = None,
    radius: float | np.ndarray = 0.01,
    collection: bpy.types.Collection | None = None,
    material: bpy.types.Material | None = None,
) -> bpy.types.Object:
    """Create a point-cloud object.

    positions: [N, 3] world coordinates; attributes: name -> [N] (float, int or bool),
    [N, 3] float (vector), [N, 4] float (linear RGBA colour) or [N, 3|4] uint8 (sRGB byte
    colour); radius: scalar or [N] point radii in
    scene units. Linked to ``collection`` (default: the scene's collection). Nothing is left
    behind on error.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ConfigError(f"positions must be [N, 3], got shape {positions.shape}")
    count = positions.shape[0]
    attributes = dict(attributes or {})
    attributes["radius"] = np.broadcast_to(np.asarray(radius, dtype=np.float32), (count,))
    specs = {key: _attribute_spec(values, count, key) for key, values in attributes.items()}

    mesh = bpy.data.meshes.new(name)
    obj = None
    try:
        mesh.vertices.add(count)
        mesh.vertices.foreach_set("co", positions.astype(np.float32).reshape(-1))
        for key, (data_type, field_name, flat) in specs.items():
            attribute = mesh.attributes.new(key, data_type, "POINT")
            attribute.data.foreach_set(field_name, flat)
        obj = bpy.data.objects.new(name, mesh)
        bpy.context.scene.collection.objects.link(obj)  # convert needs it in the view layer
        with bpy.context.temp_override(
            active_object=obj, object=obj, selected_objects=[obj], selected_editable_objects=[obj]
        ):
            result = bpy.ops.object.convert(target="POINTCLOUD")
        if result != {"FINISHED"} or obj.type != "POINTCLOUD":
            raise RuntimeError(f"converting '{name}' to a point cloud failed: {result}")
        bpy.context.scene.collection.objects.unlink(obj)
        if collection is None:
            collection = bpy.context.scene.collection
        collection.objects.link(obj)
    except Exception:
        if obj is not None:
            data = obj.data
            bpy.data.objects.remove(obj)
            if data is not None and data != mesh and data.users == 0:
                bpy.data.pointclouds.remove(data)
        if mesh.users == 0:
            bpy.data.meshes.remove(mesh)
        raise
    if mesh.users == 0:
        bpy.data.meshes.remove(mesh)
    cloud = obj.data
    cloud.name = name
    selection = cloud.attributes.get(".select_vert")
    if selection is not None:
        cloud.attributes.remove(selection)
    if material is not None:
        cloud.materials.append(material)
    return obj


def read_point_attribute(obj: bpy.types.Object, name: str) -> np.ndarray:
    """Read a point attribute back as numpy: [N] or [N, C] (byte colours: sRGB in [0, 1])."""
    attribute = obj.data.attributes[name]
    count = len(attribute.data)
    width = {"FLOAT": 1, "INT": 1, "BOOLEAN": 1, "FLOAT_VECTOR": 3, "FLOAT_COLOR": 4, "BYTE_COLOR": 4}[
        attribute.data_type
    ]
    # byte colours come back as the stored sRGB values in [0, 1] (exactly byte / 255)
    field_name = {"FLOAT_VECTOR": "vector", "FLOAT_COLOR": "color", "BYTE_COLOR": "color_srgb"}.get(
        attribute.data_type, "value"
    )
    dtype = {"INT": np.int32, "BOOLEAN": bool}.get(attribute.data_type, np.float32)
    values = np.zeros(count * width, dtype=dtype)
    attribute.data.foreach_get(field_name, values)
    return values.reshape(count, width) if width > 1 else values
