"""Terrain and rock meshes: positions from the heightfield, outward winding, sizes."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.terrain import TerrainConfig, generate_terrain
from esgs.core.terrain.mesh import heightfield_mesh, rock_mesh, rocks_mesh, terrain_mesh


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


@pytest.fixture(scope="module")
def terrain():
    config = TerrainConfig(resolution=65, extent_m=30.0, relief_amplitude_m=0.6, relief_wavelength_m=10.0,
                           crater_count=5, rock_abundance=0.08, rock_min_diameter_m=0.4, rock_max_diameter_m=1.5)
    return generate_terrain(config, seed=2)


def test_heightfield_mesh_matches_heights_and_faces_up(terrain):
    vertices, faces = heightfield_mesh(terrain)
    assert vertices.shape == (65 * 65, 3) and faces.shape == (2 * 64 * 64, 3)
    np.testing.assert_allclose(vertices[:, 2], terrain.heights.ravel(), atol=1e-6)
    np.testing.assert_allclose(vertices[:, 2], terrain.height_at(vertices[:, 0], vertices[:, 1]), atol=1e-5)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    assert np.all(normals[:, 2] > 0)
    # Total projected area is the square.
    assert 0.5 * normals[:, 2].sum() == pytest.approx(30.0 ** 2)


def test_decimated_mesh_keeps_the_edges(terrain):
    vertices, faces = heightfield_mesh(terrain, stride=5)
    assert vertices[:, 0].min() == -15.0 and vertices[:, 0].max() == 15.0
    assert vertices[:, 1].min() == -15.0 and vertices[:, 1].max() == 15.0
    assert faces.max() == vertices.shape[0] - 1


def test_rock_mesh_is_closed_outward_and_unit_sized():
    vertices, faces = rock_mesh(12345)
    assert vertices[:, 2].min() == pytest.approx(0.0) and vertices[:, 2].max() == pytest.approx(1.0)
    assert max(np.ptp(vertices[:, 0]), np.ptp(vertices[:, 1])) == pytest.approx(1.0)
    assert signed_volume(vertices, faces) > 0.1
    # Closed: every edge is shared by exactly two faces.
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)
    np.testing.assert_array_equal(rock_mesh(12345)[0], vertices)
    assert not np.allclose(rock_mesh(54321)[0], vertices)


def test_rocks_are_placed_scaled_and_embedded(terrain):
    rocks = terrain.rocks
    vertices, faces = rocks_mesh(rocks)
    per_rock = vertices.shape[0] // len(rocks)
    blobs = vertices.reshape(len(rocks), per_rock, 3)
    np.testing.assert_allclose(blobs[:, :, 2].min(axis=1), rocks[:, 2], atol=1e-9)
    np.testing.assert_allclose(np.ptp(blobs[:, :, 2], axis=1), rocks[:, 4], rtol=1e-9)
    horizontal = np.linalg.norm(blobs[:, :, :2] - rocks[:, None, :2], axis=2).max(axis=1)
    assert np.all(horizontal <= 0.75 * rocks[:, 3]) and np.all(horizontal >= 0.35 * rocks[:, 3])
    assert faces.shape[0] % len(rocks) == 0 and faces.max() == vertices.shape[0] - 1
    assert signed_volume(vertices, faces) > 0


def test_terrain_mesh_combines_ground_and_rocks(terrain):
    ground_vertices, ground_faces = heightfield_mesh(terrain)
    rock_vertices, rock_faces = rocks_mesh(terrain.rocks)
    vertices, faces = terrain_mesh(terrain)
    assert vertices.shape[0] == ground_vertices.shape[0] + rock_vertices.shape[0]
    assert faces.shape[0] == ground_faces.shape[0] + rock_faces.shape[0]
    np.testing.assert_array_equal(vertices[ground_vertices.shape[0]:], rock_vertices)
    without = terrain_mesh(terrain, include_rocks=False)
    np.testing.assert_array_equal(without[1], ground_faces)
