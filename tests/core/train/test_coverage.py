"""unseen_ground: surface pixels of a view that no training view sees."""
from __future__ import annotations

import numpy as np
import torch

from esgs.core.train.coverage import training_depths, unseen_ground
from esgs.core.train.dataset import View
from esgs.core.train.gaussians import GaussianModel


def _plane(x_range=(-4.0, 4.0), z=5.0, step=0.1) -> GaussianModel:
    xs = torch.arange(x_range[0], x_range[1] + 1e-6, step)
    ys = torch.arange(-2.0, 2.0 + 1e-6, step)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    count = len(grid)
    means = torch.cat([grid, torch.full((count, 1), z)], 1)
    return GaussianModel.from_tensors(means=means, sh_dc=torch.zeros(count, 1, 3), sh_rest=torch.zeros(count, 0, 3),
                                      opacity_logit=torch.full((count,), 5.0),
                                      log_scales=torch.full((count, 3), float(np.log(0.08))),
                                      quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(count, 1), max_sh_degree=0)


def _view(index: int, centre_x: float, width: int = 64, height: int = 32) -> View:
    K = torch.tensor([[20.0, 0.0, width / 2], [0.0, 20.0, height / 2], [0.0, 0.0, 1.0]])
    viewmat = torch.eye(4)
    viewmat[0, 3] = -centre_x  # camera at (centre_x, 0, 0) looking along +z
    return View(index=index, name=f"v{index}.png", K=K, viewmat=viewmat, width=width, height=height,
                image=torch.zeros(height, width, 3, dtype=torch.uint8))


def test_ground_outside_every_training_view_is_marked():
    params = _plane().render_params(0)
    held_out = _view(0, 0.0)  # sees the whole plane: x in [-4, 4] -> columns 16..48
    train = [_view(1, -6.0)]  # sees world x in [-14, 2] at z = 5
    unseen = unseen_ground(params, held_out, train)
    rows = slice(12, 20)
    # world x > 2 (columns > 40) was never seen; x < 1.5 (columns < 38) was
    assert unseen[rows, 42:47].mean() > 0.95
    assert unseen[rows, 18:37].mean() < 0.02
    # no surface, no mark (outside the plane)
    assert not unseen[:, :14].any() and not unseen[:, 51:].any()
    # a second training view covering the rest leaves nothing unseen; precomputed depths give the same answer
    both = [_view(1, -6.0), _view(2, 6.0)]
    assert unseen_ground(params, held_out, both).sum() == 0
    np.testing.assert_array_equal(unseen_ground(params, held_out, train, train_depths=training_depths(params, train)),
                                  unseen)


def test_ground_hidden_behind_nearer_relief_in_training_views_is_unseen():
    far, strip = _plane(), _plane(x_range=(-0.5, 0.5), z=2.5)
    scene = GaussianModel.from_tensors(**{name: torch.cat([far.params[name], strip.params[name]])
                                          for name in far.params}, max_sh_degree=0)
    params = scene.render_params(0)
    # the training camera at x = 0 sees the far plane except x in [-1, 1], behind the strip;
    # the held-out camera at x = 3 sees that part (columns 17..23) past the strip's edge
    unseen = unseen_ground(params, _view(0, 3.0), [_view(1, 0.0)])
    rows = slice(12, 20)
    assert unseen[rows, 18:23].mean() > 0.95
    assert unseen[rows, 26:36].mean() < 0.02  # far plane at x in [1.5, 4]: seen
    assert unseen[rows, 5:12].mean() < 0.02  # the strip itself: seen
    # with the relief test off (tolerance huge) the hidden part would count as seen
    assert unseen_ground(params, _view(0, 3.0), [_view(1, 0.0)], depth_tolerance=10.0)[rows, 18:23].mean() < 0.05


def test_true_depth_replaces_the_rendered_one_when_given():
    params = _plane().render_params(0)
    held_out, train = _view(0, 0.0), [_view(1, -6.0)]
    # the truth says there is ground at z = 5 over the whole image, also where the model has nothing
    unseen = unseen_ground(params, held_out, train, depth=np.full((32, 64), 5.0), surface=np.ones((32, 64), bool))
    rows = slice(12, 20)
    assert unseen[rows, :12].mean() > 0.95  # world x < -5: the training view renders nothing there
    assert unseen[rows, 42:47].mean() > 0.95  # world x > 2: outside the training view
    assert unseen[rows, 18:37].mean() < 0.02
    # pixels the truth calls sky are never marked
    sky = np.zeros((32, 64), bool)
    assert not unseen_ground(params, held_out, train, depth=np.full((32, 64), 5.0), surface=sky).any()


def test_the_report_marks_the_held_out_views_of_a_trained_run(fast_config, tmp_path):
    from esgs.core.apps.report import unseen_ground_masks
    from esgs.core.train import train

    result = train(fast_config(out=tmp_path / "run", iterations=20))
    masks = unseen_ground_masks(result.run_dir, ["view_000", "view_008", "view_001", "no_such_view"])
    assert set(masks) == {"view_000", "view_008"}  # every 8th view is held out; view_001 trained
    for mask in masks.values():
        assert mask.dtype == bool and mask.shape == (24, 32)
        # the plane is seen from every training view: at most a thin border is unseen
        assert mask.mean() < 0.25
