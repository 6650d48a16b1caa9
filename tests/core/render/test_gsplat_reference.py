"""Our projection and SH against gsplat's pure-torch reference (``gsplat/cuda/_torch_impl.py``).

gsplat (1.5.3, the field's reference implementation; its CUDA kernels build only when called,
and nothing here calls them) ships readable torch statements of its kernels. These tests
compare our rule with them on random Gaussians and several cameras, in float64:

- **projection** (``core/render/projection.py`` in torch, the Numba kernels of the CPU
  backend, and the ``meta`` of :func:`esgs.core.render.rasterization` on the reference and
  CPU backends) against ``_fully_fused_projection``: centres (means2d), conics of the dilated
  2D covariance, camera depths, the antialiasing compensation, and which Gaussians the
  near / far planes cull. The same conventions on both sides: the 2D covariance is dilated
  by ``eps2d`` = 0.3 px^2 (our classic mode's fixed 0.3, or ``eps2d`` when antialiased), the
  Jacobian is taken at the image-plane position clamped to the image widened by
  0.3 tan(fov / 2) = 15 % of its size on each side (our ``JACOBIAN_MARGIN``), and
  the antialiased compensation is sqrt(det(cov) / det(cov + eps2d I)).
- **radii**, an intended difference: gsplat's torch reference gives per-axis radii
  ceil(3.33 sigma) (3.33 ~ sqrt(2 ln 255): where an opacity-1 Gaussian falls to 1/255), ours
  are opacity-aware (the half extent where opacity exp(-q / 2) >= 1/255, the larger axis,
  docs/rasterizer.md rule 7) and use the exact sqrt(2 ln 255) = 3.3290. So ours are never
  larger than gsplat's larger axis, and equal to it for opacity 1 unless an integer falls
  between 3.3290 sigma and 3.33 sigma. Which Gaussians count as on screen also differs at
  the image border (ours: a pixel centre inside the box; gsplat: the box overlaps the image),
  so only the near-plane culling is compared exactly.
- **SH** (``core/render/sh.py``) against ``_eval_sh_bases_fast`` / ``_spherical_harmonics``,
  degrees 0..3: the same basis, order and signs; gsplat's ``rasterization`` adds the +0.5
  offset and clamps at 0 after ``_spherical_harmonics``, as we do in ``evaluate_sh_colors``.
"""
from __future__ import annotations

import math

import pytest
import torch

gsplat_torch = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat (test-only reference) is not installed")

from esgs.core.render import rasterization
from esgs.core.render.cpu import project as project_numba
from esgs.core.render.projection import project_gaussians
from esgs.core.render.sh import evaluate_sh_colors, sh_basis

from .scenes import random_scene

WIDTH, HEIGHT = 40, 30
NEAR, FAR = 0.05, 100.0


def _scene(seed: int, *, opacity_one: bool = False) -> dict:
    """Random Gaussians in front of 3 cameras, plus the awkward ones: behind the cameras, just
    behind and just beyond the near plane, beyond the far plane, far outside the view (the
    Jacobian clamp), very flat and very large."""
    scene = random_scene(300, seed=seed, width=WIDTH, height=HEIGHT, cameras=3)
    means, scales = scene["means"].clone(), scene["scales"].clone()
    generator = torch.Generator().manual_seed(seed + 100)
    means[:20, 1] *= -1  # behind every camera
    # camera 0 sits at the origin looking along +y: depth = y there
    means[20:30, 1] = NEAR * torch.linspace(0.5, 0.99, 10, dtype=torch.float64)  # in front, inside the near plane
    means[30:40, 1] = NEAR * torch.linspace(1.01, 2.0, 10, dtype=torch.float64)  # just beyond it
    means[30:40, [0, 2]] = 0.01 * torch.randn(10, 2, generator=generator, dtype=torch.float64)
    means[40:45, 1] = 2.0 * FAR  # beyond the far plane
    means[45:70, 0] = torch.linspace(-30.0, 30.0, 25, dtype=torch.float64)  # far to the sides: clamped Jacobian
    means[70:80, 2] = torch.linspace(-20.0, 20.0, 10, dtype=torch.float64)  # far above and below
    scales[80:90, 2] = 1e-6  # flat
    scales[90:95] = 3.0  # huge
    scene["means"], scene["scales"] = means, scales
    if opacity_one:
        scene["opacities"] = torch.ones_like(scene["opacities"])
    return scene


def _gsplat_projection(scene: dict, *, eps2d: float, compensations: bool):
    covars, _ = gsplat_torch._quat_scale_to_covar_preci(scene["quats"], scene["scales"], compute_preci=False)
    return gsplat_torch._fully_fused_projection(scene["means"], covars, scene["viewmats"], scene["Ks"], WIDTH, HEIGHT,
                                                eps2d=eps2d, near_plane=NEAR, far_plane=FAR,
                                                calc_compensations=compensations)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("antialiased, eps2d", [(False, 0.3), (True, 0.3), (True, 0.1)])
@pytest.mark.parametrize("ours", [project_gaussians, project_numba], ids=["torch", "numba"])
def test_projection_matches_gsplat(ours, antialiased, eps2d, seed):
    scene = _scene(seed)
    mine = ours(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["viewmats"], scene["Ks"],
                WIDTH, HEIGHT, near_plane=NEAR, far_plane=FAR, antialiased=antialiased, eps2d=eps2d,
                need_normals=False)
    # our classic mode always dilates by 0.3 (3DGS); gsplat's eps2d is that dilation
    radii, means2d, depths, conics, compensations = _gsplat_projection(
        scene, eps2d=eps2d if antialiased else 0.3, compensations=antialiased)

    in_range = (depths > NEAR) & (depths < FAR)
    assert torch.equal(mine["valid"], in_range)  # the near / far planes cull the same Gaussians
    assert not radii[~in_range].any()
    valid = mine["valid"]
    assert valid.sum() > 600 and (~valid).sum() > 50  # 3 cameras x 300 Gaussians, the culled cases included
    # camera z of every Gaussian, culled or not (the Numba kernel sums in another order: the last bits)
    assert torch.allclose(mine["depths"], depths, rtol=1e-13, atol=1e-13)
    assert torch.allclose(mine["means2d"][valid], means2d[valid], rtol=1e-12, atol=1e-9)
    assert torch.allclose(mine["conics"][valid], conics[valid], rtol=1e-9, atol=1e-12)
    # the dilated covariance's diagonal: what the radii are taken from
    det = conics[..., 0] * conics[..., 2] - conics[..., 1] ** 2
    diagonal = torch.stack([conics[..., 2], conics[..., 0]], dim=-1) / det[..., None]
    assert torch.allclose(mine["cov_diagonal"][valid], diagonal[valid], rtol=1e-8)
    if antialiased:
        expected = scene["opacities"][None].expand_as(depths) * compensations
        assert torch.allclose(mine["opacities"][valid], expected[valid], rtol=1e-9, atol=1e-12)
    else:
        assert torch.equal(mine["opacities"], scene["opacities"][None].expand_as(depths))


@pytest.mark.parametrize("backend", ["reference", "cpu"])
@pytest.mark.parametrize("opacity_one", [True, False])
def test_rasterization_meta_matches_gsplat(backend, opacity_one):
    scene = _scene(3, opacity_one=opacity_one)
    with torch.no_grad():
        _, _, meta = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                   scene["colors"], scene["viewmats"], scene["Ks"], WIDTH, HEIGHT, near_plane=NEAR,
                                   far_plane=FAR, backend=backend)
    radii, means2d, depths, _, _ = _gsplat_projection(scene, eps2d=0.3, compensations=False)
    mine = meta["radii"].long()
    theirs = radii.long().amax(-1)  # gsplat: per-axis radii; ours: the larger half side
    assert torch.allclose(meta["depths"], depths, rtol=1e-13, atol=1e-13)
    drawn = mine > 0
    assert drawn.sum() > 500
    assert torch.allclose(meta["means2d"][drawn], means2d[drawn], rtol=1e-12, atol=1e-9)
    assert not mine[(depths <= NEAR) | (depths >= FAR)].any()  # culled by the planes: radius 0 on both sides
    assert bool((theirs[drawn] > 0).all())  # what we draw, gsplat draws too
    assert bool((mine <= theirs).all())  # opacity-aware and sqrt(2 ln 255) < 3.33: never larger
    if opacity_one:
        # the same extent but for the constant's last digits: an integer between 3.3290 and 3.33 sigma
        assert (mine[drawn] == theirs[drawn]).double().mean() > 0.99


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_matches_gsplat(degree):
    generator = torch.Generator().manual_seed(degree)
    directions = torch.randn(500, 3, generator=generator, dtype=torch.float64)
    directions[:3] = torch.eye(3, dtype=torch.float64)  # the axes, where one band's terms vanish
    unit = directions / directions.norm(dim=-1, keepdim=True)
    count = (degree + 1) ** 2
    assert torch.allclose(sh_basis(degree, unit), gsplat_torch._eval_sh_bases_fast(count, unit), rtol=1e-12,
                          atol=1e-14)
    # colours from coefficients with more bands than used (the extra ones must be ignored by both)
    coefficients = 0.4 * torch.randn(500, 16, 3, generator=generator, dtype=torch.float64)
    theirs = torch.clamp_min(gsplat_torch._spherical_harmonics(degree, directions, coefficients) + 0.5, 0.0)
    ours = evaluate_sh_colors(degree, coefficients, directions)
    assert torch.allclose(ours, theirs, rtol=1e-12, atol=1e-14)
    assert bool((theirs == 0).any()) or degree == 0  # the clamp at 0 is exercised


def test_rasterization_with_sh_renders_gsplat_colours():
    """The whole path: rendering SH (colour towards each camera centre) equals rendering the
    colours gsplat's SH gives for the same view directions."""
    scene = random_scene(60, seed=5, width=24, height=18, cameras=2, sh_degree=3)
    for cam in range(2):
        viewmat, K = scene["viewmats"][cam:cam + 1], scene["Ks"][cam:cam + 1]
        centre = -viewmat[0, :3, :3].T @ viewmat[0, :3, 3]
        colours = torch.clamp_min(gsplat_torch._spherical_harmonics(3, scene["means"] - centre, scene["colors"]) + 0.5,
                                  0.0)
        with torch.no_grad():
            from_sh, _, _ = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                          scene["colors"], viewmat, K, 24, 18, sh_degree=3, backend="reference")
            from_colours, _, _ = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                               colours, viewmat, K, 24, 18, backend="reference")
        assert from_sh.abs().max() > 0.1
        assert torch.allclose(from_sh, from_colours, rtol=1e-12, atol=1e-12)


def test_the_3_33_sigma_of_gsplat_is_the_opacity_one_level():
    """Why opacity-1 radii agree: gsplat's 3.33 rounds sqrt(2 ln 255), our 1/255 level."""
    assert math.sqrt(2.0 * math.log(255.0)) == pytest.approx(3.33, abs=1e-3)
