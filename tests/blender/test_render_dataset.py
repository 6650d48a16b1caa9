"""Rendering a synthetic scene and exporting the scene folder (tiny scenes, a few samples)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
trimesh = pytest.importorskip("trimesh")

from esgs.core.colmap import read_model  # noqa: E402
from esgs.core.config import config_to_dict  # noqa: E402
from esgs.core.errors import ConfigError  # noqa: E402
from esgs.core.formats.imageio import read_depth_exr, read_image, read_normal_exr  # noqa: E402
from esgs.core.terrain import RenderConfig, RigConfig, SceneConfig, TerrainConfig  # noqa: E402


def tiny_config(seed: int = 5, views: int = 3, sky: bool = True, **render) -> SceneConfig:
    """A 40 m terrain with craters and rocks, an orbit of ``views`` cameras at 128x72."""
    config = SceneConfig(
        name="tiny", seed=seed, sky=sky,
        terrain=TerrainConfig(resolution=129, extent_m=40.0, relief_amplitude_m=1.0, relief_wavelength_m=20.0,
                              crater_count=6, crater_max_diameter_m=8.0, rock_abundance=0.08,
                              rock_min_diameter_m=0.4, rock_max_diameter_m=1.5),
        rig=RigConfig(kind="orbit", views=views, radius_m=10.0, height_m=4.0),
        render=RenderConfig(**{"width": 128, "height": 72, "samples": 4, "camera": "custom", **render}),
    )
    config.validate()
    return config


def build_and_render(out: Path, config: SceneConfig, **kwargs) -> tuple[Path, dict]:
    from esgs.esgs_addon.render_dataset import render_dataset
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = build_terrain_scene(config)
    return render_dataset(objects, out, **kwargs), objects


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("render") / "scene"
    build_and_render(out, tiny_config())
    return out


def _view(scene: Path, image):
    model = read_model(scene)
    camera = model.cameras[image.camera_id]
    stem = Path(image.name).stem
    depth, depth_meta = read_depth_exr(scene / "priors" / "gt" / "depth" / f"{stem}.exr")
    normals, normal_meta = read_normal_exr(scene / "priors" / "gt" / "normal" / f"{stem}.exr")
    return camera, depth, depth_meta, normals, normal_meta


def test_folder_layout_and_metadata(rendered):
    info = json.loads((rendered / "scene.json").read_text())
    assert info["config"] == config_to_dict(tiny_config())
    assert info["seed"] == 5 and info["units"] == "m"
    assert info["normal_frame"] == "camera_opencv" and info["depth"] == "z_along_camera_m"
    assert info["priors"] == {"gt": ["depth", "normal", "mask"]}
    names = sorted(info["images"])
    assert len(names) == 3
    for name in names:
        stem = Path(name).stem
        assert read_image(rendered / "images" / name).shape == (72, 128, 3)
        mask = read_image(rendered / "priors" / "gt" / "mask" / f"{stem}.png")
        depth, _ = read_depth_exr(rendered / "priors" / "gt" / "depth" / f"{stem}.exr")
        assert set(np.unique(mask)) <= {0, 255}
        np.testing.assert_array_equal(mask == 255, depth > 0)
    assert not any(p.name.startswith(".") for p in rendered.rglob("*")), "scratch files left behind"


def test_loads_with_pycolmap_and_read_model(rendered):
    pycolmap = pytest.importorskip("pycolmap")
    reconstruction = pycolmap.Reconstruction(str(rendered / "sparse" / "0"))
    model = read_model(rendered)
    assert reconstruction.num_images() == len(model.images) == 3
    assert reconstruction.num_points3D() == len(model.points) > 100
    for camera in model.cameras.values():
        assert camera.model == "PINHOLE" and (camera.width, camera.height) == (128, 72)
        fx, fy, cx, cy = camera.params
        expected = tiny_config().render.focal_px
        assert fx == pytest.approx(expected, rel=1e-12) and fy == pytest.approx(expected, rel=1e-12)
        assert (cx, cy) == (64.0, 36.0)


def test_depth_and_normals_agree_with_mesh_ray_casts(rendered):
    mesh = trimesh.load(rendered / "mesh" / "ground_truth.ply", process=False)
    vertex_normals = np.asarray(mesh.vertex_normals)
    model = read_model(rendered)
    rng = np.random.default_rng(0)
    relative_errors, angles_deg = [], []
    for image in model.sorted_images():
        camera, depth, depth_meta, normals, normal_meta = _view(rendered, image)
        assert depth_meta["frame"] == "camera_opencv" and depth_meta["units"] == "m"
        assert normal_meta["frame"] == "camera_opencv"
        K, rotation, centre = camera.K(), image.rotation_matrix(), image.camera_center()
        u = rng.integers(0, camera.width, 150)
        v = rng.integers(0, camera.height, 150)
        rays = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones(len(u))], axis=1)
        hits, ray_index, triangle_index = mesh.ray.intersects_location(
            np.repeat(centre[None], len(u), axis=0), rays @ rotation, multiple_hits=False)
        # every pixel with a rendered surface must be hit, and vice versa
        has_surface = depth[v, u] > 0
        hit = np.zeros(len(u), dtype=bool)
        hit[ray_index] = True
        assert np.mean(hit == has_surface) > 0.98
        seen = depth[v[ray_index], u[ray_index]] > 0
        ray_depth = (hits - centre) @ rotation[2]
        rendered_depth = depth[v[ray_index], u[ray_index]]
        relative_errors.append(np.abs(rendered_depth - ray_depth)[seen] / ray_depth[seen])
        # the shading normal Cycles used: vertex normals interpolated at the hit point
        barycentric = trimesh.triangles.points_to_barycentric(mesh.triangles[triangle_index], hits)
        expected = np.einsum("ij,ijk->ik", barycentric, vertex_normals[mesh.faces[triangle_index]])
        expected = expected / np.linalg.norm(expected, axis=1, keepdims=True) @ rotation.T
        got = normals[v[ray_index], u[ray_index]]
        np.testing.assert_allclose(np.linalg.norm(got[seen], axis=1), 1.0, atol=1e-4)
        cosine = np.clip(np.sum(got * expected, axis=1)[seen], -1, 1)
        angles_deg.append(np.degrees(np.arccos(cosine)))
    assert np.median(np.concatenate(relative_errors)) <= 1e-3
    assert np.median(np.concatenate(angles_deg)) <= 2.0


def test_points3d_reproject_onto_matching_depth(rendered):
    model = read_model(rendered)
    depths = {image.image_id: _view(rendered, image)[1] for image in model.images.values()}
    checked = 0
    for point in model.points.values():
        assert point.track_length >= 2
        for image_id, index in zip(point.track_image_ids, point.track_point2d_idxs):
            image = model.images[int(image_id)]
            camera = model.cameras[image.camera_id]
            local = image.rotation_matrix() @ point.xyz + image.translation
            assert local[2] > 0
            u, v = (camera.K() @ (local / local[2]))[:2]
            np.testing.assert_allclose(image.points2d[index], (u, v), atol=1e-6)
            assert image.point3d_ids[index] == point.point3d_id
            assert 0 <= u < camera.width and 0 <= v < camera.height
            rendered_depth = depths[int(image_id)][int(v), int(u)]
            # nearest pixel: allow the depth change across half a pixel at grazing angles
            assert abs(rendered_depth - local[2]) <= 0.05 * local[2]
            checked += 1
    assert checked > 200


def test_same_seed_gives_identical_colmap_files(rendered, tmp_path):
    again, _ = build_and_render(tmp_path / "again", tiny_config())
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (again / "sparse" / "0" / name).read_bytes() == (rendered / "sparse" / "0" / name).read_bytes(), name


def test_grayscale_camera_writes_grey_images(tmp_path):
    scene, _ = build_and_render(tmp_path / "grey", tiny_config(views=2, grayscale=True), points_per_view=50)
    image = read_image(scene / "images" / "view_000.png")
    assert image.shape == (72, 128)
    colours = np.stack([point.rgb for point in read_model(scene).points.values()])
    assert np.all(colours[:, 0] == colours[:, 1]) and np.all(colours[:, 1] == colours[:, 2])


def test_existing_output_is_refused_before_rendering(rendered):
    from esgs.esgs_addon.render_dataset import render_dataset
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = build_terrain_scene(tiny_config(views=1))
    before = (rendered / "scene.json").stat().st_mtime_ns
    with pytest.raises(ConfigError, match="already exists"):
        render_dataset(objects, rendered)
    assert (rendered / "scene.json").stat().st_mtime_ns == before


def test_failure_mid_render_leaves_no_output(tmp_path, monkeypatch):
    import esgs.core.formats.imageio as imageio
    from esgs.esgs_addon.render_dataset import render_dataset
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = build_terrain_scene(tiny_config(views=2))
    calls = []
    real = imageio.write_normal_exr

    def fail_on_second_view(*args, **kwargs):
        calls.append(args[0])
        if len(calls) == 2:
            raise OSError("disk full (simulated)")
        return real(*args, **kwargs)

    monkeypatch.setattr(imageio, "write_normal_exr", fail_on_second_view)
    scene = bpy.context.scene
    compositor_before = scene.compositing_node_group
    with pytest.raises(OSError, match="simulated"):
        render_dataset(objects, tmp_path / "out")
    assert len(calls) == 2
    assert list(tmp_path.iterdir()) == [], "a partial folder was left behind"
    assert scene.compositing_node_group == compositor_before
    assert not [group for group in bpy.data.node_groups if group.name.startswith("ESGS pass")]


@pytest.mark.slow
def test_sfm_registers_most_views(tmp_path):
    from esgs.core.terrain import load_preset

    config = load_preset("cratered_plain", seed=2, views=10, resolution=(320, 180), samples=8)
    scene, _ = build_and_render(tmp_path / "sfm", config, sfm=True)
    info = json.loads((scene / "scene.json").read_text())
    assert info["sfm"]["total"] == 10
    assert info["sfm"]["ratio"] >= 0.9
    assert read_model(scene / "sparse_sfm" / "0").images


def test_render_operator_writes_the_generated_scene(tmp_path):
    settings = bpy.context.scene.esgs.terrain
    settings.preset = "rocky_slope"
    settings.seed = 1
    settings.views = 2
    settings.width, settings.height, settings.samples = 64, 64, 1
    settings.points_per_view = 100
    assert bpy.ops.esgs.generate_terrain() == {"FINISHED"}
    settings.output_dir = str(tmp_path / "from_operator")
    assert bpy.ops.esgs.render_dataset() == {"FINISHED"}
    info = json.loads((tmp_path / "from_operator" / "scene.json").read_text())
    assert info["config"]["name"] == "rocky_slope" and info["grayscale"] is True  # a Navcam-like preset
    assert len(read_model(tmp_path / "from_operator").images) == 2
    # the rendered folder leads into Training: it is the scene to compute priors for and train
    assert bpy.context.scene.esgs.training.scene_dir == str(tmp_path / "from_operator")
    assert bpy.ops.esgs.compute_priors.poll()
    from esgs.esgs_addon.training_job import find_scene_dir

    assert find_scene_dir(bpy.context.scene, bpy.context.scene.esgs.training.scene_dir) == tmp_path / "from_operator"
    # a second run into the same folder is refused and reported, not raised
    bpy.context.scene.esgs.training.scene_dir = ""
    with pytest.raises(RuntimeError, match="already exists"):
        bpy.ops.esgs.render_dataset()
    assert bpy.context.scene.esgs.training.scene_dir == ""  # a refused render chooses nothing


def test_esgs_scene_command_end_to_end(tmp_path, capsys):
    from esgs.core.cli import main

    out = tmp_path / "cli"
    status = main(["scene", "--preset", "cratered_plain", "--seed", "4", "--views", "2", "--resolution", "64x36",
                   "--samples", "1", "--points-per-view", "100", "--out", str(out), "--events", str(tmp_path / "ev.jsonl")])
    assert status == 0
    info = json.loads((out / "scene.json").read_text())
    assert info["seed"] == 4 and info["config"]["rig"]["views"] == 2
    assert (info["config"]["render"]["width"], info["config"]["render"]["height"]) == (64, 36)
    events = [json.loads(line) for line in (tmp_path / "ev.jsonl").read_text().splitlines()]
    assert any(event["stage"] == "render" and event["step"] == 2 for event in events)
    assert events[-1]["kind"] == "done"


def test_esgs_scene_command_rejects_bad_settings_without_rendering(tmp_path, capsys):
    from esgs.core.cli import main

    out = tmp_path / "bad"
    assert main(["scene", "--preset", "cratered_plain", "--resolution", "4x4", "--out", str(out)]) == 2
    assert "render.width" in capsys.readouterr().err
    assert main(["scene", "--preset", "no_such_preset", "--out", str(out)]) == 2
    assert "unknown scene preset" in capsys.readouterr().err
    assert not out.exists()


def test_objects_outside_the_scene_are_not_rendered(tmp_path):
    from esgs.esgs_addon.render_dataset import render_dataset
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = build_terrain_scene(tiny_config(views=1))
    # a large plane between the camera and the ground: it would cover the whole view
    camera_height = float(objects["cameras"][0].matrix_world.translation.z)
    ground_top = float(objects["terrain_data"].heights.max())
    plane_height = (camera_height + ground_top) / 2
    mesh = bpy.data.meshes.new("blocker")
    mesh.from_pydata([(-100, -100, plane_height), (100, -100, plane_height), (100, 100, plane_height),
                      (-100, 100, plane_height)], [], [(0, 1, 2, 3)])
    blocker = bpy.data.objects.new("blocker", mesh)
    bpy.context.scene.collection.objects.link(blocker)
    scene = render_dataset(objects, tmp_path / "scene", points_per_view=50)
    assert not blocker.hide_render, "hidden objects must be shown again"
    model = read_model(scene)
    image = model.sorted_images()[0]
    depth, _ = read_depth_exr(scene / "priors" / "gt" / "depth" / "view_000.exr")
    K = model.cameras[image.camera_id].K()
    rows, cols = np.nonzero(depth > 0)
    assert len(rows) > 0.5 * depth.size
    pixels = np.stack([cols + 0.5, rows + 0.5, np.ones(len(rows))], axis=1)
    local = (pixels @ np.linalg.inv(K).T) * depth[rows, cols, None]
    world = (local - image.translation) @ image.rotation_matrix()
    assert world[:, 2].max() < plane_height - 0.1
