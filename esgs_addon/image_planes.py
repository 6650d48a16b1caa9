"""Image planes: each photo shown on a rectangle in front of its camera, filling its view.

The plane's corners are the image corners back-projected to a chosen depth along the
camera's z axis, so from the camera the photo lines up with the scene exactly. Planes are
parented to their camera (moving the camera moves its photo) and hidden from renders so
they never occlude the scene when rendering from another camera. The material is an
image texture feeding an emission shader (the photo is already lit) and the texture node
is the active one, so Solid view in 'Texture' colour mode shows it too.
"""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from ..core.errors import ConfigError, DatasetError


def plane_corners_camera(K: np.ndarray, width: int, height: int, distance: float) -> np.ndarray:
    """[4, 3] image corners (top-left, top-right, bottom-right, bottom-left) at ``distance``, OpenCV axes."""
    if distance <= 0:
        raise ConfigError(f"image plane distance must be positive, got {distance}")
    pixels = np.array([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]])
    rays = np.linalg.solve(np.asarray(K, dtype=np.float64), np.vstack([pixels.T, np.ones(4)])).T
    return rays / rays[:, 2:3] * distance


def load_image(path: str | Path) -> bpy.types.Image:
    """Load an image file into bpy.data (reusing one already loaded); DatasetError if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError("image file not found", path=path, hint="check the scene's images/ folder")
    try:
        return bpy.data.images.load(str(path), check_existing=True)
    except RuntimeError as error:
        raise DatasetError(f"Blender cannot read this image: {error}", path=path) from error


def image_material(image: bpy.types.Image, name: str) -> bpy.types.Material:
    """An unlit material showing ``image`` through the plane's UVs."""
    material = bpy.data.materials.new(name)
    tree = material.node_tree
    tree.nodes.clear()
    texture = tree.nodes.new("ShaderNodeTexImage")
    texture.image = image
    texture.interpolation = "Linear"
    texture.extension = "CLIP"
    texture.location = (-400, 0)
    emission = tree.nodes.new("ShaderNodeEmission")
    emission.location = (-150, 0)
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    output.location = (100, 0)
    tree.links.new(texture.outputs["Color"], emission.inputs["Color"])
    tree.links.new(emission.outputs["Emission"], output.inputs["Surface"])
    tree.nodes.active = texture
    return material


def image_plane_object(
    name: str,
    camera_object: bpy.types.Object,
    K: np.ndarray,
    width: int,
    height: int,
    image: bpy.types.Image,
    distance: float,
    collection: bpy.types.Collection,
) -> bpy.types.Object:
    """Create the plane showing ``image`` at ``distance`` in front of ``camera_object``.

    K: [3, 3] the camera's intrinsics (pixels). The plane is parented to the camera with
    vertices in the camera's local frame (Blender axes: x right, y up, -z forward).
    """
    corners = plane_corners_camera(K, width, height, distance)
    corners_blender = corners * np.array([1.0, -1.0, -1.0])  # OpenCV -> Blender camera axes
    mesh = bpy.data.meshes.new(name)
    created: list = [mesh]
    try:
        mesh.vertices.add(4)
        mesh.vertices.foreach_set("co", corners_blender.astype(np.float32).reshape(-1))
        mesh.loops.add(4)
        # counter-clockwise seen from the camera (normal towards it): TL, BL, BR, TR
        mesh.loops.foreach_set("vertex_index", np.array([0, 3, 2, 1], dtype=np.int32))
        mesh.polygons.add(1)
        mesh.polygons.foreach_set("loop_start", np.array([0], dtype=np.int32))
        uv_layer = mesh.uv_layers.new(name="UVMap")
        # image v runs bottom-up in Blender: top-left corner is (0, 1)
        uv_layer.data.foreach_set("uv", np.array([0, 1, 0, 0, 1, 0, 1, 1], dtype=np.float32))
        mesh.update(calc_edges=True)
        material = image_material(image, name)
        created.append(material)
        mesh.materials.append(material)
        obj = bpy.data.objects.new(name, mesh)
        created.append(obj)
        obj.parent = camera_object
        obj.matrix_parent_inverse.identity()
        obj.hide_render = True
        obj["esgs_image_plane_distance"] = float(distance)
        collection.objects.link(obj)
    except Exception:
        bpy.data.batch_remove(created)
        raise
    return obj
