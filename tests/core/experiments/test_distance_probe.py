"""benchmarks/distance_probe.py: the count of training views whose frustum holds a point."""
from __future__ import annotations

import numpy as np

from esgs.core.colmap.io import read_model
from tests.core.experiments.helpers import load_benchmark_script
from tests.core.train.scene import make_scene


def load_probe():
    return load_benchmark_script("distance_probe")


def test_views_seeing_counts_training_frusta_only(tmp_path):
    probe = load_probe()
    scene = make_scene(tmp_path / "scene", views=9)
    images = read_model(scene).sorted_images()
    # a point on each view's optical axis, 1 unit ahead, lies in that view's frustum
    ahead = []
    for image in images:
        camera_to_world = np.linalg.inv(image.world_to_camera())
        ahead.append(camera_to_world[:3, 3] + camera_to_world[:3, 2])
    ahead = np.array(ahead)
    counts = probe.views_seeing(ahead, scene)
    everything = probe.views_seeing(ahead, scene, test_every=0)
    for index in range(len(images)):
        held_out = index % 8 == 0
        assert everything[index] >= 1  # its own view sees it
        assert everything[index] - counts[index] == sum(
            1 for other in (0, 8) if other < len(images) and _sees(images[other], read_model(scene), ahead[index]))
        assert held_out or counts[index] >= 1
    # a point behind every camera is seen by none
    centres = np.array([np.linalg.inv(image.world_to_camera())[:3, 3] for image in images])
    backwards = np.array([np.linalg.inv(image.world_to_camera())[:3, 2] for image in images]).mean(axis=0)
    assert probe.views_seeing((centres.mean(axis=0) - 1e3 * backwards)[None], scene)[0] == 0


def _sees(image, model, point) -> bool:
    camera = model.cameras[image.camera_id]
    local = image.world_to_camera()[:3, :3] @ point + image.world_to_camera()[:3, 3]
    if local[2] <= 0:
        return False
    u, v = (camera.K() @ local)[:2] / local[2]
    return 0 <= u < camera.width and 0 <= v < camera.height
