"""A terrain mesh rebuilt on the CPU from a scene's own images and poses (``--reconstruct``).

Never the exact mesh, never trained Gaussians: only ``images/`` and ``sparse/0`` (poses,
intrinsics; the sparse points give each view's depth range and the ground plane, never
mesh vertices). Steps:

1. **Depth per view**: multi-view plane-sweep stereo with ZNCC (:mod:`.stereo`), fronto-
   parallel and ground-parallel planes, each view against its best neighbours.
2. **Cross-view check**: a depth survives when at least ``min_agreeing`` neighbours'
   depth maps agree within ``consistency_tolerance`` (relative) at its projection.
3. **Fusion**: the surviving pixels are lifted to a world point cloud.
4. **Meshing (2.5D)**: terrain is a height field over its ground plane (a least-squares
   plane through the fused points). Points are binned on a grid in that plane (cell side:
   ``cell_factor`` times the median pixel footprint); each cell keeps the median height of
   its points (robust to stereo outliers), cells whose height departs from their
   neighbourhood's median by more than ``spike_threshold`` cells are dropped; the cell
   points are triangulated with a 2D Delaunay triangulation (scipy) and triangles with an
   edge longer than ``max_edge_cells`` times the local sample spacing are removed, so gaps
   stay gaps instead of being bridged by long flat triangles. The local spacing is the
   larger of the cell and the ground footprint of a pixel there (``cell_factor`` x depth /
   focal, divided by the sine of the grazing angle, at most 20x), so the sparsely sampled
   far range still meshes. Overhangs cannot be represented (rare on terrain).
5. **Free-space carving** (optional, ``carve_tolerance`` > 0): a triangle that some view sees
   *through* (a consistent stereo depth
   of that view lies clearly behind the triangle on the same ray) is removed. On rover views
   the far range is sampled sparsely and long triangles bridge the valleys hidden behind each
   ridge; rendered, such a bridge stands in front of the slope the camera really sees, and its
   labels come out tens of percent too near. Removing it lets the rendering reach the surface
   behind it (or leaves a hole for the prior's fill). Off by default: it also removes the chords
   a height field draws across a crater's concave far wall, which are somewhat too near but
   cover it (docs/labels.md).

The mesh is written to ``SCENE/mesh/reconstructed.ply`` (world frame and units of the COLMAP
model), with a report of every stage.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..errors import ConfigError, DatasetError
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..formats.scene_dir import SceneDir, gap_mesh_path
from .stereo import StereoOptions, View, consistent_depths, depth_maps



@dataclass
class ReconstructOptions:
    """Settings of the CPU mesh reconstruction (see the module docstring)."""

    stereo: StereoOptions = field(default_factory=StereoOptions)
    consistency_tolerance: float = field(default=0.01, metadata={"help": "relative depth agreement between views"})
    min_agreeing: int = field(default=1, metadata={"help": "neighbour views that must confirm a depth"})
    cell_factor: float = field(default=2.0, metadata={"help": "grid cell side in median pixel footprints"})
    max_edge_cells: float = field(default=4.0, metadata={"help": "remove triangles with a longer edge (in cells)"})
    spike_threshold: float = field(default=3.0, metadata={
        "help": "drop cells this many cells above/below their neighbourhood"})
    max_width: int = field(default=960, metadata={
        "help": "shrink wider images to this width for stereo (cost grows with pixels; 0 = full size)"})
    carve_tolerance: float = field(default=0.0, metadata={
        "help": "remove triangles a view's stereo depth lies behind by more than this relative depth "
                "(free-space carving; 0 = off)"})
    carve_min_hits: int = field(default=2, metadata={
        "help": "samples of a triangle (4 per view) that must be seen through before it is removed"})

    def validate(self) -> None:
        self.stereo.validate()
        if self.consistency_tolerance <= 0:
            raise ConfigError(f"consistency_tolerance must be positive, got {self.consistency_tolerance}")
        if self.min_agreeing < 0:
            raise ConfigError(f"min_agreeing must be >= 0, got {self.min_agreeing}")
        for name in ("cell_factor", "max_edge_cells", "spike_threshold"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")
        if self.carve_tolerance < 0:
            raise ConfigError(f"carve_tolerance must be >= 0 (0 = off), got {self.carve_tolerance}")
        if self.carve_min_hits < 1:
            raise ConfigError(f"carve_min_hits must be >= 1, got {self.carve_min_hits}")
        if self.max_width != 0 and self.max_width < 32:
            raise ConfigError(f"max_width must be 0 (full size) or at least 32 pixels, got {self.max_width}")


def _grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image.astype(np.float32)
    return (image[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32))


def fit_ground_plane(points: np.ndarray, camera_centers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit normal [3], centroid [3]) of the least-squares plane through ``points`` [N, 3],
    the normal oriented towards the mean camera centre (the cameras are above the ground)."""
    centroid = np.median(points, axis=0)
    _, _, vt = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)
    normal = vt[2]
    if (camera_centers.mean(axis=0) - centroid) @ normal < 0:
        normal = -normal
    return normal / np.linalg.norm(normal), centroid


def load_views(scene_dir: str | Path, margin: float, ground_normal: np.ndarray | None,
               max_width: int = 0) -> tuple[list[View], Any]:
    """The scene's views for stereo: grey images, K, poses, depth ranges from the sparse points.

    An image that sees fewer than 3 sparse points in front of it has no depth range and is left
    out of stereo (the labels rendered from the mesh still cover it); fewer than two views left
    is a DatasetError.

    max_width: images wider than this are shrunk (area averaging) with K scaled to match
    (pixel coordinates scale about the top-left corner, COLMAP's origin); 0 keeps them.
    """
    from ..colmap.io import load_scene
    from ..formats.imageio import read_image

    model, images_dir = load_scene(scene_dir)
    if not model.images:
        raise DatasetError("the COLMAP model has no images", path=scene_dir)
    if len(model.images) < 2:
        raise DatasetError("one image cannot be reconstructed by stereo", path=scene_dir,
                           hint="--reconstruct needs overlapping views from different positions; give a --mesh instead")
    xyz_by_id = {point_id: point.xyz for point_id, point in model.points.items()}
    views = []
    for image in model.sorted_images():
        camera = model.cameras[image.camera_id]
        if not camera.is_pinhole:
            raise DatasetError(f"camera {camera.camera_id} is {camera.model}: stereo needs undistorted pinhole views",
                               path=scene_dir, hint="undistort the scene first (esgs colmap undistort)")
        ids = [int(i) for i in np.asarray(image.point3d_ids) if int(i) in xyz_by_id]
        if not ids:  # no tracks stored: every point in front of the camera
            ids = list(xyz_by_id)
        if not ids:
            raise DatasetError("the COLMAP model has no 3D points: the depth range of the views is unknown",
                               path=scene_dir, hint="run SfM (esgs dataset from-images) so the model has points3D")
        world_to_camera = image.world_to_camera()
        xyz = np.array([xyz_by_id[i] for i in ids])
        in_camera = xyz @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        z = in_camera[:, 2]
        z = z[z > 0]
        if len(z) < 3:
            continue  # its depth range is unknown: no stereo from it (its labels still come from the mesh)
        near, far = np.percentile(z, [1, 99])
        ground_offsets = None
        if ground_normal is not None:
            offsets = in_camera @ (world_to_camera[:3, :3] @ ground_normal)
            # the ground normal points at the cameras, so ground points have n.X < 0 in camera frame
            offsets = -offsets[in_camera[:, 2] > 0]
            if len(offsets) >= 3 and np.percentile(offsets, 1) > 0:
                low, high = np.percentile(offsets, [1, 99])
                ground_offsets = (float(low / margin), float(high * margin))
        grey, K = _grey(read_image(images_dir / image.name)), camera.K()
        if max_width and grey.shape[1] > max_width:
            import cv2

            factor = max_width / grey.shape[1]
            size = (max_width, max(1, round(grey.shape[0] * factor)))
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
            K = np.diag([size[0] / camera.width, size[1] / camera.height, 1.0]) @ K
        views.append(View(image.name, grey, K, world_to_camera, (float(near / margin), float(far * margin)),
                          frozenset(ids), ground_offsets))
    if len(views) < 2:
        raise DatasetError(f"only {len(views)} of {len(model.images)} images see 3 or more sparse points in front of "
                           "them: stereo needs two", path=scene_dir,
                           hint="run SfM with more features (esgs dataset from-images) or give a --mesh instead")
    return views, model


class HeightfieldMesh(NamedTuple):
    """What :func:`mesh_from_points` builds: the kept surface and the gap triangles it removed."""

    vertices: np.ndarray  # [V, 3]
    triangles: np.ndarray  # [F, 3] int64
    stats: dict[str, Any]
    gap_vertices: np.ndarray  # [G, 3]: the long triangles that would have bridged a gap
    gap_triangles: np.ndarray  # [E, 3] int64


def _compact(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Only the vertices the triangles use, and the triangles renumbered."""
    used = np.unique(triangles)
    remap = -np.ones(len(vertices), np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[triangles]


#: Cells compared with each cell in the spike test (the nearest, within 2.5 sample spacings).
NEIGHBOURS = 25


def mesh_from_points(points: np.ndarray, normal: np.ndarray, cell: float, max_edge_cells: float,
                     spike_threshold: float, footprints: np.ndarray | None = None) -> HeightfieldMesh:
    """2.5D mesh of ``points`` [N, 3] over the plane with unit ``normal`` [3].

    cell: grid cell side (scene units). footprints: [N] optional spacing of each point's
    neighbours on the ground (a pixel's footprint seen at its grazing angle); a triangle is
    kept when its longest edge is at most ``max_edge_cells`` times the larger of ``cell`` and
    its vertices' footprints, so the far range (sparser samples) still meshes while real
    gaps stay open. Returns a :class:`HeightfieldMesh`: the kept triangles counter-clockwise
    seen from the normal's side, statistics, and the removed long triangles as a separate
    gap mesh (:mod:`.gaps` finds the labels that look through them). See the module
    docstring for the steps.
    """
    from scipy.spatial import Delaunay, cKDTree

    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    axis_u = np.cross(normal, helper)
    axis_u /= np.linalg.norm(axis_u)
    axis_v = np.cross(normal, axis_u)
    planar = np.stack([points @ axis_u, points @ axis_v], axis=1)
    height = points @ normal
    spacing = np.full(len(points), cell) if footprints is None else np.maximum(np.asarray(footprints, np.float64), cell)
    cells = np.floor((planar - planar.min(axis=0)) / cell).astype(np.int64)
    # one id per occupied cell, without a dense grid (the far range of a horizon view spans km)
    _, flat = np.unique(cells, axis=0, return_inverse=True)
    flat = flat.reshape(-1)
    order = np.lexsort((height, flat))  # by cell, then by height inside the cell
    flat_sorted = flat[order]
    starts = np.flatnonzero(np.r_[True, flat_sorted[1:] != flat_sorted[:-1]])
    counts = np.diff(np.r_[starts, len(flat_sorted)])
    medians = height[order][starts + counts // 2]  # median height per cell: robust to stereo outliers
    centres = np.stack([np.add.reduceat(planar[order, 0], starts), np.add.reduceat(planar[order, 1], starts)], 1)
    centres /= counts[:, None]
    cell_spacing = np.minimum.reduceat(spacing[order], starts)
    # spikes: compare each cell with the median height of the cells around it
    # (at most NEIGHBOURS cells within the radius: a ball query's lists grow without bound where
    # far-range cells of rover views get radii of tens of metres, and ran out of memory there)
    tree = cKDTree(centres)
    k = min(NEIGHBOURS, len(centres))
    distances, neighbours = tree.query(centres, k=k)
    distances, neighbours = distances.reshape(len(centres), k), neighbours.reshape(len(centres), k)
    radius = 2.5 * np.maximum(cell_spacing, cell)
    near = distances <= radius[:, None]
    local = np.nanmedian(np.where(near, medians[neighbours], np.nan), axis=1)
    spike = np.abs(medians - local) > spike_threshold * np.maximum(cell_spacing, cell)
    keep = ~spike
    u, v, h, vertex_spacing = centres[keep, 0], centres[keep, 1], medians[keep], cell_spacing[keep]
    if len(u) < 3:
        raise DatasetError("too few consistent stereo points to build a mesh",
                           hint="the views may not overlap, or the images lack texture; give a --mesh instead")
    triangulation = Delaunay(np.stack([u, v], axis=1))
    triangles = triangulation.simplices.astype(np.int64)
    vertices = np.outer(u, axis_u) + np.outer(v, axis_v) + np.outer(h, normal)
    corners = vertices[triangles]
    edges = np.stack([np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1),
                      np.linalg.norm(corners[:, 2] - corners[:, 1], axis=1),
                      np.linalg.norm(corners[:, 0] - corners[:, 2], axis=1)], axis=1)
    short = edges.max(axis=1) <= max_edge_cells * vertex_spacing[triangles].max(axis=1)
    # orient counter-clockwise seen from the normal's side (face normals towards the cameras)
    corners = vertices[triangles]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    flip = face_normals @ normal < 0
    triangles[flip] = triangles[flip][:, [0, 2, 1]]
    gaps = triangles[~short]
    triangles = triangles[short]
    stats = {"cells": int(len(starts)), "spikes_removed": int(spike.sum()), "triangles": int(len(triangles)),
             "long_triangles_removed": int(len(gaps)), "cell_size": float(cell)}
    kept_vertices, kept_triangles = _compact(vertices, triangles)
    gap_vertices, gap_triangles = _compact(vertices, gaps) if len(gaps) else (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    return HeightfieldMesh(kept_vertices, kept_triangles, stats, gap_vertices, gap_triangles)


#: Barycentric weights of the points of a triangle that free-space carving looks at: its
#: centroid and a point towards each corner (a bridge is often seen through on one side only).
CARVE_SAMPLES = np.array([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])


def seen_through(vertices: np.ndarray, triangles: np.ndarray, views: list[View], depths: list[np.ndarray],
                 tolerance: float) -> np.ndarray:
    """[F] int: per triangle, how many of its sample points (:data:`CARVE_SAMPLES`, in every
    view) have that view's depth map (0 = none) farther than ``(1 + tolerance)`` times the
    point's own depth at the pixel they project to: the view sees past the triangle there,
    so the triangle stands in space the camera saw empty."""
    samples = np.einsum("sk,fkd->fsd", CARVE_SAMPLES, vertices[triangles]).reshape(-1, 3)
    hits = np.zeros(len(samples), np.int64)
    for view, depth in zip(views, depths):
        in_view = samples @ view.world_to_camera[:3, :3].T + view.world_to_camera[:3, 3]
        z = in_view[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (in_view @ view.K.T)[:, :2] / z[:, None]
        height, width = depth.shape
        front = (z > 0) & np.isfinite(uv).all(axis=1)
        u = np.floor(np.where(front, uv[:, 0], -1)).astype(np.int64)
        v = np.floor(np.where(front, uv[:, 1], -1)).astype(np.int64)
        inside = front & (u >= 0) & (v >= 0) & (u < width) & (v < height)
        behind = np.zeros(len(samples))
        behind[inside] = depth[v[inside], u[inside]]
        hits += (behind > z * (1.0 + tolerance)).astype(np.int64)
    return hits.reshape(len(triangles), len(CARVE_SAMPLES)).sum(axis=1)


def carve_free_space(mesh: HeightfieldMesh, views: list[View], depths: list[np.ndarray], tolerance: float,
                     min_hits: int) -> HeightfieldMesh:
    """``mesh`` without the triangles the views see through (:func:`seen_through` at least
    ``min_hits`` times); the carved count is added to its statistics. The carved triangles are
    not gaps: a label that looks through one sees what the camera saw."""
    hits = seen_through(mesh.vertices, mesh.triangles, views, depths, tolerance)
    keep = hits < min_hits
    stats = {**mesh.stats, "carved_triangles": int((~keep).sum()), "triangles": int(keep.sum())}
    if keep.all():
        return mesh._replace(stats=stats)
    if not keep.any():
        raise DatasetError("free-space carving removed every triangle of the mesh",
                           hint="raise --carve-tolerance, or 0 to switch carving off")
    vertices, triangles = _compact(mesh.vertices, mesh.triangles[keep])
    return mesh._replace(vertices=vertices, triangles=triangles, stats=stats)


def reconstruct_mesh(scene_dir: str | Path, options: ReconstructOptions | None = None, *,
                     out_path: str | Path | None = None, progress: ProgressCallback = no_progress) -> dict[str, Any]:
    """Rebuild a terrain mesh from the scene's images and poses and write it as a PLY.

    out_path: default ``SCENE/mesh/reconstructed.ply`` (written atomically). Returns a report
    ``{"mesh": path, "views", "fused_points", "mesh stats...", "seconds", "options"}``.
    Raises :class:`DatasetError` for a scene without images, points or overlap.
    """
    from .mesh_io import write_mesh

    options = options or ReconstructOptions()
    options.validate()
    scene_dir = Path(scene_dir)
    start = time.perf_counter()
    from ..colmap.io import read_model

    model = read_model(scene_dir)
    xyz, _, _, _ = model.points_arrays()
    centers = np.stack([image.camera_center() for image in model.sorted_images()]) if model.images else np.zeros((0, 3))
    ground_normal = None
    if len(xyz) >= 3 and len(centers):
        ground_normal, _ = fit_ground_plane(xyz, centers)
    views, model = load_views(scene_dir, options.stereo.depth_margin, ground_normal, options.max_width)
    total = len(views) + 2
    without_points = sorted({image.name for image in model.images.values()} - {view.name for view in views})
    if without_points:
        progress(ProgressEvent(0, total, "stereo", kind="message",
                               message=f"no stereo from {', '.join(without_points)}: fewer than 3 sparse points in front"))

    def sweep_progress(step: int, count: int, name: str) -> None:
        progress(ProgressEvent(step, total, "stereo", message=f"depth of {name}"))

    depths, neighbours = depth_maps(views, options.stereo, ground_normal_world=ground_normal, progress=sweep_progress)
    raw_fraction = float(np.mean([np.mean(d > 0) for d in depths]))
    depths = consistent_depths(views, depths, neighbours, options.consistency_tolerance, options.min_agreeing)
    points, footprints = [], []
    for view, depth in zip(views, depths):
        rows, cols = np.nonzero(depth > 0)
        z = depth[rows, cols].astype(np.float64)
        rays = np.stack([cols + 0.5, rows + 0.5, np.ones_like(z)], axis=1) @ np.linalg.inv(view.K).T
        camera_to_world = np.linalg.inv(view.world_to_camera)
        points.append((rays * z[:, None]) @ camera_to_world[:3, :3].T + camera_to_world[:3, 3])
        # a pixel's footprint on the ground: z / f across the ray, stretched by the grazing angle
        directions = rays @ camera_to_world[:3, :3].T
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        footprints.append((z / view.K[0, 0], directions))
    points_all = np.concatenate(points) if points else np.zeros((0, 3))
    if len(points_all) < 3:
        raise DatasetError("stereo found no consistent depth in any view", path=scene_dir,
                           hint="the views may not overlap or lack texture; give a --mesh instead")
    progress(ProgressEvent(len(views) + 1, total, "fuse", message=f"{len(points_all)} fused points",
                           metrics={"points": float(len(points_all))}))
    normal, _ = fit_ground_plane(points_all, centers)
    across = np.concatenate([size for size, _ in footprints])
    grazing = np.abs(np.concatenate([directions for _, directions in footprints]) @ normal)
    ground_footprints = options.cell_factor * across / np.maximum(grazing, 0.05)
    cell = options.cell_factor * float(np.median(across))
    built = mesh_from_points(points_all, normal, cell, options.max_edge_cells, options.spike_threshold,
                             ground_footprints)
    if options.carve_tolerance > 0:
        built = carve_free_space(built, views, depths, options.carve_tolerance, options.carve_min_hits)
    mesh_path = Path(out_path) if out_path is not None else SceneDir(scene_dir).reconstructed_mesh
    gaps_path = gap_mesh_path(mesh_path)
    # the gap mesh first: a mesh file never sits beside a gap mesh of another run
    if len(built.gap_triangles):
        write_mesh(gaps_path, built.gap_vertices, built.gap_triangles)
    else:
        gaps_path.unlink(missing_ok=True)
    write_mesh(mesh_path, built.vertices, built.triangles)
    progress(ProgressEvent(total, total, "mesh", kind="done", message=f"mesh written: {mesh_path}",
                           metrics={"triangles": float(len(built.triangles))}))
    return {"mesh": str(mesh_path), "gaps": str(gaps_path) if len(built.gap_triangles) else None,
            "views": len(views), "views_without_points": without_points, "stereo_fraction": raw_fraction,
            "consistent_fraction": float(np.mean([np.mean(d > 0) for d in depths])),
            "fused_points": int(len(points_all)), **built.stats, "seconds": round(time.perf_counter() - start, 2),
            "neighbours": {view.name: [views[j].name for j in nbrs] for view, nbrs in zip(views, neighbours)},
            "options": asdict(options)}
