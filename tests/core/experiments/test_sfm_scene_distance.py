"""The acceptance study's point-to-mesh distance is the exact kernel of ``esgs compare``."""
import numpy as np

from esgs.core.experiments import sfm_scene
from esgs.core.labels import write_mesh
from esgs.core.metrics.geometry import point_to_mesh_distances


def test_sfm_scene_distance_is_the_compare_kernel_with_known_distances(tmp_path):
    # unit square in z = 0 (two triangles); distances known in closed form
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    mesh_path = tmp_path / "square.ply"
    write_mesh(mesh_path, vertices, faces)
    points = np.array([
        [0.5, 0.5, 2.0],    # above the interior: its height
        [0.25, 0.75, -0.3],  # below: unsigned
        [0.0, 0.0, 0.0],    # on a corner
        [2.0, 0.5, 0.0],    # beside an edge, in the plane: 1 to the edge x = 1
        [2.0, 2.0, 1.0],    # beyond the corner (1, 1, 0): sqrt(1 + 1 + 1)
        [0.5, -1.0, 1.0],   # beyond the edge y = 0: sqrt(1 + 1)
    ])
    expected = np.array([2.0, 0.3, 0.0, 1.0, np.sqrt(3.0), np.sqrt(2.0)])
    measured = sfm_scene.point_to_mesh_distances(points, mesh_path)
    np.testing.assert_allclose(measured, expected, atol=1e-12)
    np.testing.assert_array_equal(measured, point_to_mesh_distances(points, vertices, faces))
