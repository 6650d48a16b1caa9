"""Render a synthetic scene with Cycles (CPU) and export it as a complete scene folder.

Public entry point: :func:`render_dataset`. For each camera of a scene built by
:func:`~.terrain_scene.build_terrain_scene` it renders the RGB image (grey for grey camera
presets) and the Depth and Normal passes, then writes (see docs/scene_format.md)::

    SCENE/images/<name>.png
    SCENE/sparse/0/                  COLMAP model of the exact cameras and points3D
    SCENE/priors/gt/depth/<stem>.exr metres along the camera z axis, 0 = no surface
    SCENE/priors/gt/normal/<stem>.exr unit normals, camera frame with OpenCV axes
    SCENE/priors/gt/mask/<stem>.png  255 = surface, 0 = sky / no surface
    SCENE/mesh/ground_truth.ply      terrain + rocks, world frame, metres
    SCENE/scene.json                 config, seed, units, frames, which priors exist
    SCENE/sparse_sfm/0/              optional: pycolmap SfM on the renders

The folder is built in a temporary sibling and renamed when complete, so a failure at any
point leaves no output folder behind.

Passes come out through one compositor File Output node per pass (single-layer 32-bit
EXR): in headless Blender 5.0 a multilayer EXR keeps only the combined image.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import bpy
import numpy as np

from ..core.errors import ConfigError, DatasetError
from ..core.progress import ProgressEvent
from ..core.formats.scene_dir import PriorSource, SceneDir

#: Cycles writes this depth where a pixel sees no surface.
_BACKGROUND_DEPTH = 1e9
#: A point is visible in a view when its depth agrees with the rendered depth (bilinear) this well...
VISIBILITY_RELATIVE_TOLERANCE = 0.01
#: ...and each of the four pixels around its projection within this: no depth edge between them.
NEIGHBOUR_RELATIVE_TOLERANCE = 0.05
_PASSES = (("Depth", "BW", "FLOAT"), ("Normal", "RGB", "VECTOR"))


def _opencv_cameras(cameras: list[bpy.types.Object], scene: bpy.types.Scene) -> list[tuple[np.ndarray, np.ndarray, int, int]]:
    from .cameras import opencv_from_camera_object

    return [opencv_from_camera_object(camera, scene) for camera in cameras]


class _PassOutputs:
    """A compositor tree routing Depth and Normal to single-layer EXRs; restores the scene after."""

    def __init__(self, scene: bpy.types.Scene, directory: Path):
        self.scene = scene
        self.directory = directory
        view_layer = scene.view_layers[0]
        self._saved = (scene.compositing_node_group, view_layer.use_pass_z, view_layer.use_pass_normal,
                       scene.render.use_compositing)
        view_layer.use_pass_z = True
        view_layer.use_pass_normal = True
        scene.render.use_compositing = True
        self.tree = bpy.data.node_groups.new("ESGS pass outputs", "CompositorNodeTree")
        scene.compositing_node_group = self.tree
        layers = self.tree.nodes.new("CompositorNodeRLayers")
        layers.scene = scene
        self.outputs = []
        for pass_name, color_mode, socket_type in _PASSES:
            node = self.tree.nodes.new("CompositorNodeOutputFile")
            node.format.media_type = "IMAGE"
            node.format.file_format = "OPEN_EXR"
            node.format.color_depth = "32"
            node.format.color_mode = color_mode
            node.format.exr_codec = "NONE"  # scratch files: speed over size
            node.directory = str(directory) + "/"
            node.file_output_items.new(socket_type, pass_name)
            self.tree.links.new(layers.outputs[pass_name], node.inputs[pass_name])
            self.outputs.append(node)

    def set_prefix(self, prefix: str) -> dict[str, Path]:
        """Name the next render's pass files ``<prefix><pass>.exr``; return their paths."""
        for node in self.outputs:
            node.file_name = prefix
        return {name: self.directory / f"{prefix}{name}.exr" for name, _, _ in _PASSES}

    def close(self) -> None:
        view_layer = self.scene.view_layers[0]
        (self.scene.compositing_node_group, view_layer.use_pass_z, view_layer.use_pass_normal,
         self.scene.render.use_compositing) = self._saved
        bpy.data.node_groups.remove(self.tree)


def depth_from_pass(raw_depth: np.ndarray) -> np.ndarray:
    """Cycles' Depth pass [H, W] -> depth [H, W] float32 with 0 where no surface (background 1e10)."""
    depth = np.asarray(raw_depth, dtype=np.float32).copy()
    depth[~np.isfinite(depth) | (depth >= _BACKGROUND_DEPTH) | (depth <= 0)] = 0.0
    return depth


def camera_normals_from_pass(world_normals: np.ndarray, world_to_camera: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """World-frame Normal pass [H, W, 3] -> unit normals [H, W, 3] in the camera frame (OpenCV axes).

    The pass averages the normals seen by a pixel's samples, so its vectors are shorter
    than 1 along edges; they are renormalised. Pixels without a surface get (0, 0, 0).
    """
    rotation = np.asarray(world_to_camera, dtype=np.float64)[:3, :3]
    normals = np.asarray(world_normals, dtype=np.float64) @ rotation.T
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    good = valid & (length[..., 0] > 1e-6)
    normals = np.where(good[..., None], normals / np.maximum(length, 1e-12), 0.0)
    return normals.astype(np.float32)


def world_mesh_arrays(objects: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices [V, 3], triangles [F, 3] int64, vertex normals [V, 3]) of terrain and rocks, world frame.

    Read from the Blender meshes that were rendered, so the ground truth is exactly what
    Cycles saw (triangulated as Cycles triangulates). The normals are the shading normals
    Cycles interpolates: Blender's vertex normals for smooth meshes; for flat meshes every
    triangle gets its own three vertices carrying the face normal.
    """
    depsgraph = bpy.context.evaluated_depsgraph_get()
    cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    vertex_blocks, triangle_blocks, normal_blocks = [], [], []
    offset = 0
    for obj in [objects["terrain"], *objects.get("rocks", [])]:
        key = obj.data.as_pointer()
        if key not in cache:
            cache[key] = _local_mesh_arrays(obj.evaluated_get(depsgraph).data)
        vertices, triangles, normals = cache[key]
        matrix = np.array(obj.matrix_world, dtype=np.float64)
        vertex_blocks.append(vertices @ matrix[:3, :3].T + matrix[:3, 3])
        # normals transform with the inverse transpose (rocks are scaled non-uniformly)
        world_normals = normals @ np.linalg.inv(matrix[:3, :3])
        normal_blocks.append(world_normals / np.linalg.norm(world_normals, axis=1, keepdims=True))
        triangle_blocks.append(triangles + offset)
        offset += len(vertices)
    return np.concatenate(vertex_blocks), np.concatenate(triangle_blocks), np.concatenate(normal_blocks)


def _local_mesh_arrays(mesh: bpy.types.Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    vertices = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", vertices)
    vertices = vertices.reshape(-1, 3).astype(np.float64)
    mesh.calc_loop_triangles()
    triangles = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", triangles)
    triangles = triangles.reshape(-1, 3).astype(np.int64)
    smooth = np.empty(len(mesh.polygons), dtype=bool)
    mesh.polygons.foreach_get("use_smooth", smooth)
    if smooth.all():
        normals = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
        mesh.vertex_normals.foreach_get("vector", normals)
        return vertices, triangles, normals.reshape(-1, 3).astype(np.float64)
    if smooth.any():
        raise DatasetError(f"mesh '{mesh.name}' mixes smooth and flat faces; the ground-truth export needs one or the other")
    corners = vertices[triangles]  # [F, 3, 3]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    face_normals /= np.linalg.norm(face_normals, axis=1, keepdims=True)
    return (corners.reshape(-1, 3), np.arange(3 * len(triangles), dtype=np.int64).reshape(-1, 3),
            np.repeat(face_normals, 3, axis=0))


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear samples of ``image`` [H, W] at COLMAP pixel coordinates (centres at +0.5).

    Returns (values [N], ok [N], corners [4, N]): ok is False outside the image or when one
    of the four neighbours is 0 (no surface), so samples never blend a surface with the sky.
    """
    height, width = image.shape
    x, y = u - 0.5, v - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < width) & (y0 + 1 < height)
    x0c, y0c = np.clip(x0, 0, width - 2), np.clip(y0, 0, height - 2)
    fx, fy = x - x0c, y - y0c
    corners = [image[y0c, x0c], image[y0c, x0c + 1], image[y0c + 1, x0c], image[y0c + 1, x0c + 1]]
    for corner in corners:
        ok &= corner > 0
    value = (corners[0] * (1 - fx) * (1 - fy) + corners[1] * fx * (1 - fy)
             + corners[2] * (1 - fx) * fy + corners[3] * fx * fy)
    return value, ok, np.stack(corners)


def sample_surface_points(depths: list[np.ndarray], images: list[np.ndarray],
                          cameras: list[tuple[np.ndarray, np.ndarray, int, int]], points_per_view: int,
                          seed: int, min_track_length: int = 2) -> dict[str, Any]:
    """Points on the rendered ground-truth surface with colours and visibility tracks.

    depths: per view [H, W] metres (0 = none); images: per view [H, W, 3] uint8;
    cameras: per view (K [3, 3], world_to_camera [4, 4], width, height).
    ``points_per_view`` pixels with a surface are drawn at random in each view and lifted
    to 3D with the rendered depth (so they lie on the surface), coloured from that pixel.
    A point's track holds every view where it projects inside the image onto a pixel
    whose rendered depth agrees within :data:`VISIBILITY_RELATIVE_TOLERANCE` (bilinear) and
    :data:`NEIGHBOUR_RELATIVE_TOLERANCE` (each of the four pixels around it): a depth test,
    so occluded views and projections straddling a depth edge are left out. Points seen in fewer than ``min_track_length`` views
    are dropped, as SfM would never have triangulated them.

    Returns xyz [P, 3], rgb [P, 3] uint8, and tracks: per view (point indices [T], uv [T, 2]).
    """
    rng = np.random.default_rng([int(seed), 0x506F696E])
    xyz_blocks, rgb_blocks = [], []
    for depth, image, (K, world_to_camera, _, _) in zip(depths, images, cameras):
        rows, cols = np.nonzero(depth > 0)
        if len(rows) == 0:
            continue
        pick = rng.choice(len(rows), size=min(points_per_view, len(rows)), replace=False)
        rows, cols = rows[pick], cols[pick]
        z = depth[rows, cols].astype(np.float64)
        pixels = np.stack([cols + 0.5, rows + 0.5, np.ones_like(z)], axis=1)
        camera_points = (pixels @ np.linalg.inv(K).T) * z[:, None]
        rotation, translation = world_to_camera[:3, :3], world_to_camera[:3, 3]
        xyz_blocks.append((camera_points - translation) @ rotation)
        colour = image[rows, cols]
        rgb_blocks.append(np.repeat(colour[:, None], 3, axis=1) if colour.ndim == 1 else colour)
    if not xyz_blocks:
        return {"xyz": np.zeros((0, 3)), "rgb": np.zeros((0, 3), np.uint8), "tracks": [(np.zeros(0, np.int64), np.zeros((0, 2)))] * len(depths)}
    xyz = np.concatenate(xyz_blocks)
    rgb = np.concatenate(rgb_blocks).astype(np.uint8)

    visible = []
    for depth, (K, world_to_camera, _, _) in zip(depths, cameras):
        camera_points = xyz @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        z = camera_points[:, 2]
        in_front = z > 1e-6
        safe_z = np.where(in_front, z, 1.0)
        u = K[0, 0] * camera_points[:, 0] / safe_z + K[0, 2]
        v = K[1, 1] * camera_points[:, 1] / safe_z + K[1, 2]
        rendered, ok, corners = _bilinear(depth, u, v)
        seen = (in_front & ok & (np.abs(rendered - z) <= VISIBILITY_RELATIVE_TOLERANCE * z)
                & np.all(np.abs(corners - z) <= NEIGHBOUR_RELATIVE_TOLERANCE * z, axis=0))
        visible.append((seen, np.stack([u, v], axis=1)))
    count = np.sum([seen for seen, _ in visible], axis=0)
    keep = np.nonzero(count >= min_track_length)[0]
    remap = -np.ones(len(xyz), dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    tracks = []
    for seen, uv in visible:
        members = np.nonzero(seen & (remap >= 0))[0]
        tracks.append((remap[members], uv[members]))
    return {"xyz": xyz[keep], "rgb": rgb[keep], "tracks": tracks}


def build_colmap_model(names: list[str], cameras: list[tuple[np.ndarray, np.ndarray, int, int]],
                       points: dict[str, Any]):
    """A ColmapModel: one PINHOLE camera per distinct (K, size), images in ``names`` order, points3D.

    Image ids are 1..N in the given order; each image's points2D are its track entries.
    """
    from ..core.colmap import Camera, ColmapModel, Image, Point3D
    from ..core.colmap.geometry import matrix_to_quat_wxyz

    colmap_cameras: dict[int, Camera] = {}
    camera_ids: dict[tuple, int] = {}
    images: dict[int, Image] = {}
    point_tracks: list[list[tuple[int, int]]] = [[] for _ in range(len(points["xyz"]))]
    for index, (name, (K, world_to_camera, width, height), (point_ids, uv)) in enumerate(
            zip(names, cameras, points["tracks"]), start=1):
        params = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        key = (params, int(width), int(height))
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            colmap_cameras[camera_ids[key]] = Camera(camera_ids[key], "PINHOLE", int(width), int(height),
                                                     np.array(params, dtype=np.float64))
        images[index] = Image(index, f"{name}.png", camera_ids[key], matrix_to_quat_wxyz(world_to_camera[:3, :3]),
                              np.array(world_to_camera[:3, 3], dtype=np.float64), np.asarray(uv, dtype=np.float64),
                              np.asarray(point_ids, dtype=np.int64) + 1)
        for point2d_index, point_id in enumerate(point_ids.tolist()):
            point_tracks[point_id].append((index, point2d_index))
    colmap_points = {}
    for point_index, track in enumerate(point_tracks):
        colmap_points[point_index + 1] = Point3D(
            point_index + 1, np.asarray(points["xyz"][point_index], dtype=np.float64), points["rgb"][point_index],
            0.0, np.array([t[0] for t in track], dtype=np.int64), np.array([t[1] for t in track], dtype=np.int64))
    return ColmapModel(colmap_cameras, images, colmap_points)


def run_sfm(images_dir: Path, output_dir: Path, work_dir: Path,
            pinhole: tuple[float, float, float, float] | None = None) -> dict[str, Any]:
    """pycolmap SfM (SIFT, exhaustive matching, incremental mapping) on the CPU.

    ``pinhole`` (fx, fy, cx, cy) fixes the intrinsics, as for a calibrated rover camera;
    without it COLMAP estimates one shared PINHOLE camera. Rover sequences move forward
    with short baselines, so the initial pair may have a small triangulation angle (4 deg
    instead of COLMAP's 16) and mostly forward motion. Writes the largest reconstruction
    to ``output_dir`` (binary) and returns ``{"registered", "total", "ratio", "points"}``.
    """
    import pycolmap

    database = work_dir / "sfm.db"
    total = len(list(images_dir.glob("*.png")))
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    if pinhole is not None:
        reader.camera_params = ",".join(repr(float(value)) for value in pinhole)
    pycolmap.extract_features(database, images_dir, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.mapper.init_min_tri_angle = 4.0
    options.mapper.init_min_num_inliers = 50
    options.mapper.init_max_forward_motion = 1.0
    options.min_model_size = 3
    if pinhole is not None:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
    maps_dir = work_dir / "sfm_maps"
    maps_dir.mkdir(parents=True, exist_ok=True)
    reconstructions = pycolmap.incremental_mapping(database, images_dir, maps_dir, options)
    if not reconstructions:
        return {"registered": 0, "total": total, "ratio": 0.0, "points": 0}
    best = max(reconstructions.values(), key=lambda r: r.num_reg_images())
    output_dir.mkdir(parents=True, exist_ok=True)
    best.write_binary(str(output_dir))
    registered = int(best.num_reg_images())
    return {"registered": registered, "total": total, "ratio": registered / max(total, 1),
            "points": int(best.num_points3D()), "intrinsics": "fixed" if pinhole is not None else "estimated"}


def render_dataset(objects: dict[str, Any], out_dir: str | Path, *, progress: Callable[[ProgressEvent], None] | None = None,
                   sfm: bool = False, overwrite: bool = False, points_per_view: int = 2000,
                   scene: bpy.types.Scene | None = None) -> Path:
    """Render every camera of a synthetic scene and write the scene folder ``out_dir``.

    objects: the dict returned by :func:`~.terrain_scene.build_terrain_scene` (or
    :func:`~.terrain_scene.scene_objects_from_collection`). Renders with Cycles on the CPU
    (the config's samples, OpenImageDenoise). ``sfm`` also runs pycolmap SfM on the renders
    into ``sparse_sfm/0`` and records its registration ratio in scene.json.
    ``points_per_view`` surface pixels per view seed the points3D. Returns ``out_dir``.
    Raises :class:`ConfigError` (an existing ``out_dir`` without ``overwrite``, a scene without
    cameras) before rendering anything.
    """
    import trimesh

    from .. import __version__
    from ..core.colmap import write_model
    from ..core.config import config_to_dict
    from ..core.formats.imageio import read_image, write_depth_exr, write_normal_exr, write_png
    from ..core.io_utils import atomic_directory, atomic_write_json
    from .terrain_scene import GENERATOR_VERSION, apply_render_settings

    out_dir = Path(out_dir)
    scene = scene or bpy.context.scene
    config = objects["config"]
    report = progress or (lambda event: None)
    cameras = sorted(objects["cameras"], key=lambda camera: camera.name)
    if not cameras:
        raise ConfigError("the scene has no cameras to render", hint="generate the scene with at least one view")
    if out_dir.exists() and not overwrite:
        raise ConfigError("output folder already exists", path=out_dir, hint="choose another folder or pass overwrite")
    if points_per_view < 1:
        raise ConfigError(f"points_per_view must be positive, got {points_per_view}")
    names = [camera.name for camera in cameras]
    if len(set(names)) != len(names) or any(not n or "/" in n or "\\" in n for n in names):
        raise ConfigError("camera names must be unique and usable as file names", hint=f"got {names}")

    apply_render_settings(scene, config.render)
    opencv = _opencv_cameras(cameras, scene)
    for (_, _, width, height), camera in zip(opencv, cameras):
        if (width, height) != (config.render.width, config.render.height):
            raise ConfigError(f"camera '{camera.name}' is {width}x{height}, the scene renders "
                              f"{config.render.width}x{config.render.height}")
    previous_camera, previous_path = scene.camera, scene.render.filepath
    total = len(cameras) + 3 + (1 if sfm else 0)
    metadata = {"generator": f"esgs synthetic Mars {GENERATOR_VERSION}", "scene": str(config.name),
                "seed": str(config.seed)}
    start = time.perf_counter()
    with atomic_directory(out_dir, overwrite=overwrite) as staging:
        staged = SceneDir(staging)
        scratch = staging / ".render_scratch"
        scratch.mkdir()
        passes = _PassOutputs(scene, scratch)
        hidden = _hide_other_objects(scene, objects)
        depths, images = [], []
        try:
            for index, (camera, (K, world_to_camera, width, height)) in enumerate(zip(cameras, opencv)):
                view_start = time.perf_counter()
                stem = camera.name
                image_name = f"{stem}.png"
                scene.camera = camera
                image_path = staged.image(image_name)
                image_path.parent.mkdir(parents=True, exist_ok=True)
                scene.render.filepath = str(image_path)
                pass_files = passes.set_prefix(f"{stem}_")
                bpy.ops.render.render(write_still=True, scene=scene.name)
                for pass_name, path in pass_files.items():
                    if not path.is_file():
                        raise DatasetError(f"Cycles did not write the {pass_name} pass", path=path)
                if not image_path.is_file():
                    raise DatasetError("Cycles did not write the image", path=image_path)
                depth = _read_single_channel(pass_files["Depth"])
                depth = depth_from_pass(depth)
                valid = depth > 0
                world_normals = _read_vector(pass_files["Normal"])
                normals = camera_normals_from_pass(world_normals, world_to_camera, valid)
                write_depth_exr(staged.depth_map(PriorSource.GT, image_name), depth, units="m",
                                frame="camera_opencv", metadata={**metadata, "invalid": "0", "mask_kind": "surface"})
                write_normal_exr(staged.normal_map(PriorSource.GT, image_name), normals,
                                 frame="camera_opencv",
                                 metadata={**metadata, "axes": "x right, y down, z forward (OpenCV)",
                                           "invalid": "0 0 0", "mask_kind": "surface"})
                write_png(staged.mask_map(PriorSource.GT, image_name), np.where(valid, 255, 0).astype(np.uint8))
                for path in pass_files.values():
                    path.unlink()
                depths.append(depth)
                images.append(read_image(image_path))
                report(ProgressEvent(index + 1, total, "render", metrics={
                    "view_s": time.perf_counter() - view_start, "surface_fraction": float(valid.mean())},
                    message=f"rendered {stem}"))
        finally:
            passes.close()
            for obj in hidden:
                obj.hide_render = False
            scene.camera, scene.render.filepath = previous_camera, previous_path

        vertices, triangles, vertex_normals = world_mesh_arrays(objects)
        mesh_path = staged.ground_truth_mesh
        mesh_path.parent.mkdir()
        trimesh.Trimesh(vertices, triangles, vertex_normals=vertex_normals, process=False).export(
            mesh_path, encoding="binary", vertex_normal=True)
        report(ProgressEvent(len(cameras) + 1, total, "export", message="ground-truth mesh written",
                             metrics={"triangles": float(len(triangles))}))

        points = sample_surface_points(depths, images, opencv, points_per_view, int(config.seed))
        model = build_colmap_model(names, opencv, points)
        write_model(model, staged.model, binary=True)
        report(ProgressEvent(len(cameras) + 2, total, "export", message="COLMAP model written",
                             metrics={"points3d": float(len(points["xyz"]))}))

        sfm_summary = None
        if sfm:
            shared_intrinsics = {tuple(np.round(K[[0, 1, 0, 1], [0, 1, 2, 2]], 9)) for K, _, _, _ in opencv}
            pinhole = tuple(opencv[0][0][[0, 1, 0, 1], [0, 1, 2, 2]]) if len(shared_intrinsics) == 1 else None
            sfm_summary = run_sfm(staged.images, staged.sfm_model, scratch, pinhole)
            report(ProgressEvent(len(cameras) + 3, total, "sfm", metrics={"registration_ratio": sfm_summary["ratio"]},
                                 message=f"SfM registered {sfm_summary['registered']}/{sfm_summary['total']} views"))

        import shutil

        shutil.rmtree(scratch)
        relative = SceneDir(Path())  # the paths scene.json names, relative to the scene folder
        atomic_write_json(staged.provenance, {
            "format": "esgs-scene",
            "format_version": 1,
            "source": "synthetic",
            "generator": "esgs.esgs_addon.terrain_scene",
            "generator_version": GENERATOR_VERSION,
            "esgs_version": __version__,
            "seed": int(config.seed),
            "config": config_to_dict(config),
            "units": "m",
            "world_frame": "metres, +z up, x east, y north, terrain centred on the origin",
            "camera_frame": "opencv (x right, y down, z forward); poses world-to-camera as in COLMAP",
            "depth": "z_along_camera_m",
            "depth_invalid": 0.0,
            "normal_frame": "camera_opencv",
            "mask": "255 surface, 0 sky or no surface",
            "priors": {"gt": ["depth", "normal", "mask"]},
            "images": [f"{name}.png" for name in names],
            "grayscale": bool(config.render.grayscale),
            "mesh": relative.ground_truth_mesh.as_posix(),
            "sparse": relative.model.as_posix(),
            "points3d": int(len(points["xyz"])),
            "sfm": sfm_summary,
            "render": {"engine": "CYCLES", "device": "CPU", "samples": int(config.render.samples),
                       "denoiser": "OPENIMAGEDENOISE", "pixel_filter": "blackman_harris 1.5 px",
                       "seconds": round(time.perf_counter() - start, 2)},
            # scenes from an external mesh (mesh_scene.py) describe their source and frame here
            **objects.get("scene_info", {}),
        })
    report(ProgressEvent(total, total, "export", kind="done", message=f"scene folder written: {out_dir}"))
    return out_dir


def _hide_other_objects(scene: bpy.types.Scene, objects: dict[str, Any]) -> list[bpy.types.Object]:
    """Hide from rendering every visible object that is not part of the synthetic scene.

    Anything else in the file (the default cube, an imported model) would show up in the
    renders and depth maps but not in the ground-truth mesh. Returns the objects hidden.
    """
    ours = {obj.as_pointer() for obj in objects["collection"].all_objects}
    hidden = []
    for obj in scene.objects:
        if obj.as_pointer() not in ours and not obj.hide_render and obj.type not in ("CAMERA", "LIGHT"):
            obj.hide_render = True
            hidden.append(obj)
    return hidden


def _read_single_channel(path: Path) -> np.ndarray:
    from ..core.formats.imageio import read_exr

    channels, _ = read_exr(path)
    if len(channels) != 1:
        raise DatasetError(f"expected one channel in Blender's depth pass, got {sorted(channels)}", path=path)
    return next(iter(channels.values()))


def _read_vector(path: Path) -> np.ndarray:
    from ..core.formats.imageio import read_exr

    channels, _ = read_exr(path)
    if not {"X", "Y", "Z"} <= set(channels):
        raise DatasetError(f"expected channels X, Y, Z in Blender's normal pass, got {sorted(channels)}", path=path)
    return np.stack([channels["X"], channels["Y"], channels["Z"]], axis=-1)
