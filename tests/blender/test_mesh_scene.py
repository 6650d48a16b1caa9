"""Scenes rendered from an external mesh: the real Mars landform (3 tiny views) and bad meshes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
trimesh = pytest.importorskip("trimesh")

from esgs.core.colmap import read_model  # noqa: E402
from esgs.core.commands.scene import SceneJob  # noqa: E402
from esgs.core.errors import DatasetError  # noqa: E402
from esgs.core.formats.imageio import read_depth_exr, read_image  # noqa: E402
from esgs.core.terrain.mesh_scene import MeshRigConfig, MeshSceneConfig  # noqa: E402
from esgs.core.terrain import RenderConfig  # noqa: E402
from tests.conftest import require_shared  # noqa: E402

MAST_HEIGHT_M = 2.0


@pytest.fixture(scope="module")
def landform_scene(tmp_path_factory) -> Path:
    """3 traverse views of the Mars landform at 96x54, rendered once for the module."""
    from esgs.esgs_addon.make_scene import make_scene

    mesh = require_shared("mars_landform", "terrain.glb")
    out = tmp_path_factory.mktemp("mesh_scene") / "landform"
    job = SceneJob(mesh=str(mesh), views=3, width=96, height=54, samples=2, seed=4, points_per_view=300,
                   mast_height_m=MAST_HEIGHT_M)
    make_scene(job, out)
    return out


@pytest.fixture(scope="module")
def ground_truth(landform_scene):
    return trimesh.load(landform_scene / "mesh" / "ground_truth.ply", process=False)


def _z_depth_by_ray_casting(mesh, image, camera, pixels: np.ndarray) -> np.ndarray:
    """Depth along the camera z axis [N] of the mesh through pixel centres [N, 2] (inf on a miss)."""
    fx, fy, cx, cy = camera.params
    rotation = image.rotation_matrix()
    rays_camera = np.stack([(pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy, np.ones(len(pixels))], axis=1)
    directions = rays_camera @ rotation  # camera -> world: R^T x, row-wise
    lengths = np.linalg.norm(directions, axis=1)
    origins = np.repeat(image.camera_center()[None], len(pixels), axis=0)
    locations, ray_index, _ = mesh.ray.intersects_location(origins, directions / lengths[:, None], multiple_hits=False)
    distance = np.full(len(pixels), np.inf)
    distance[ray_index] = np.linalg.norm(locations - origins[ray_index], axis=1)
    return distance / lengths  # the z component of a unit ray is 1 / |(x, y, 1)|


def test_rendered_depth_agrees_with_ray_casting_the_ground_truth(landform_scene, ground_truth):
    model = read_model(landform_scene / "sparse" / "0")
    assert len(model.images) == 3
    rng = np.random.default_rng(0)
    for image in model.images.values():
        camera = model.cameras[image.camera_id]
        depth, _ = read_depth_exr(landform_scene / "priors" / "gt" / "depth" / f"{Path(image.name).stem}.exr")
        assert depth.shape == (54, 96)
        assert (depth > 0).mean() > 0.99, "the rig must only see terrain"
        rows, cols = np.nonzero(depth > 0)
        pick = rng.choice(len(rows), size=150, replace=False)
        pixels = np.stack([cols[pick] + 0.5, rows[pick] + 0.5], axis=1)
        reference = _z_depth_by_ray_casting(ground_truth, image, camera, pixels)
        assert np.isfinite(reference).mean() > 0.98
        hit = np.isfinite(reference)
        relative = np.abs(depth[rows[pick], cols[pick]][hit] - reference[hit]) / reference[hit]
        assert np.median(relative) <= 1e-3, f"{image.name}: median relative depth error {np.median(relative):.2e}"


def test_ground_truth_is_the_ply_geometry_in_blender_frame(landform_scene, ground_truth):
    reference = trimesh.load(require_shared("mars_landform", "terrain_geometry.ply"), process=False)
    assert len(ground_truth.vertices) == len(reference.vertices)
    assert len(ground_truth.faces) == len(reference.faces)
    np.testing.assert_allclose(ground_truth.bounds, reference.bounds, atol=1e-4)
    ours = np.unique(np.round(np.asarray(ground_truth.vertices, np.float64), 3), axis=0)
    theirs = np.unique(np.round(np.asarray(reference.vertices, np.float64), 3), axis=0)
    np.testing.assert_allclose(ours, theirs, atol=2e-3)
    info = json.loads((landform_scene / "scene.json").read_text())
    assert info["source"] == "mesh" and info["mesh_source"]["triangles"] == len(reference.faces)


def test_sparse_points_lie_on_the_mesh_and_cameras_at_mast_height(landform_scene, ground_truth):
    model = read_model(landform_scene / "sparse" / "0")
    xyz = np.stack([point.xyz for point in model.points.values()])
    assert len(xyz) > 300
    sample = xyz[np.random.default_rng(1).choice(len(xyz), size=min(300, len(xyz)), replace=False)]
    _, distance, _ = trimesh.proximity.closest_point(ground_truth, sample)
    assert np.median(distance) < 1e-3 and np.quantile(distance, 0.95) < 2e-2
    # neighbouring views overlap strongly: many points are seen by all three views
    tracks = np.array([len(point.track_image_ids) for point in model.points.values()])
    assert (tracks == 3).mean() > 0.3
    centres = np.stack([image.camera_center() for image in model.images.values()])
    locations, index, _ = ground_truth.ray.intersects_location(centres, np.tile([0.0, 0.0, -1.0], (len(centres), 1)),
                                                               multiple_hits=False)
    heights = np.linalg.norm(locations - centres[index], axis=1)
    np.testing.assert_allclose(heights, MAST_HEIGHT_M, atol=1e-3)
    first = read_image(landform_scene / "images" / "view_000.png")
    assert first.std() > 5.0, "the texture must show (an unlit, grey photograph)"


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    lines = [f"v {x} {y} {z}" for x, y, z in vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def _small_plane(path: Path, size: float) -> Path:
    """A wavy square surface of side ``size`` metres (OBJ is Y up: Blender makes its y the height)."""
    axis = np.linspace(-size / 2, size / 2, 21)
    x, z = np.meshgrid(axis, axis)
    y = 0.3 * np.sin(x / 3.0) * np.cos(z / 4.0)
    vertices = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    faces = []
    for row in range(20):
        for col in range(20):
            a = row * 21 + col
            faces += [(a, a + 21, a + 1), (a + 1, a + 21, a + 22)]
    return _write_obj(path, vertices, np.array(faces))


def _config(mesh: Path, **rig) -> MeshSceneConfig:
    return MeshSceneConfig(mesh=str(mesh), name=mesh.stem, seed=0, rig=MeshRigConfig(**rig),
                           render=RenderConfig(width=32, height=18, samples=1))


def _data_counts() -> tuple[int, ...]:
    return tuple(len(getattr(bpy.data, kind)) for kind in ("objects", "meshes", "materials", "collections", "cameras"))


def test_missing_and_empty_files_name_the_file(tmp_path):
    with pytest.raises(DatasetError, match="not found") as error:
        SceneJob(mesh=str(tmp_path / "nowhere.glb")).scene_config()
    assert "nowhere.glb" in str(error.value)
    empty = tmp_path / "empty.glb"
    empty.write_bytes(b"")
    with pytest.raises(DatasetError, match="empty.glb"):
        SceneJob(mesh=str(empty)).scene_config()


def test_bad_meshes_raise_and_leave_nothing_behind(tmp_path):
    from esgs.esgs_addon.mesh_scene import build_mesh_scene

    garbage = tmp_path / "garbage.glb"
    garbage.write_bytes(b"glTF not really a binary glTF file" * 10)
    no_faces = _write_obj(tmp_path / "points.obj", np.random.default_rng(0).normal(size=(10, 3)), np.zeros((0, 3), int))
    small = _small_plane(tmp_path / "small.obj", size=10.0)
    before = _data_counts()
    for path, message in ((garbage, "could not read"), (no_faces, "no faces"), (small, "could not place")):
        with pytest.raises(DatasetError, match=message) as error:
            build_mesh_scene(_config(path, border_margin_m=20.0, max_attempts=20))
        assert path.name in str(error.value)
        assert _data_counts() == before


@pytest.mark.parametrize("kind", ["traverse", "orbit"])
def test_rigs_are_deterministic_and_see_only_surface(tmp_path, kind):
    from esgs.esgs_addon.mesh_scene import build_mesh_scene

    mesh = _small_plane(tmp_path / "plane.obj", size=80.0)
    rig = {"kind": kind, "views": 4, "border_margin_m": 25.0, "orbit_radius_m": 8.0}
    first = build_mesh_scene(_config(mesh, **rig))
    poses = [pose.world_to_camera for pose in first["poses"]]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    again = build_mesh_scene(_config(mesh, **rig))
    np.testing.assert_array_equal(poses, [pose.world_to_camera for pose in again["poses"]])
    centres = np.stack([pose.camera_center for pose in again["poses"]])
    # the OBJ's +Y up became +Z up; the surface lies within +-0.3 m of z = 0
    assert np.all(np.abs(centres[:, :2]) < 40.0 - (25.0 if kind == "traverse" else 0.0))
    if kind == "traverse":
        np.testing.assert_allclose(np.linalg.norm(np.diff(centres[:, :2], axis=0), axis=1), 1.0, rtol=1e-9)
        assert np.all((centres[:, 2] > 1.6) & (centres[:, 2] < 2.4))
    else:
        target = again["poses"][0].target
        np.testing.assert_allclose(np.linalg.norm(centres[:, :2] - target[:2], axis=1), 8.0, rtol=1e-9)
