"""``esgs priors-export --format 3dgs``: read back with a reader written from the reference code's format.

Format (graphdeco-inria gaussian-splatting, depth regularisation): ``depths/<stem>.png`` 16-bit grey,
value / 2^16 = mono inverse depth; ``sparse/0/depth_params.json`` = {stem: {"scale", "offset"}};
the trainer uses ``png / 2^16 * scale + offset`` as the inverse depth (1 / camera z) of the SfM model.
"""
import json

import cv2
import numpy as np
import pytest

from esgs.core.cli import main
from esgs.core.priors.io import write_prior_maps
from tests.blender.colmap_helpers import synthetic_model, write_scene


def _read_3dgs(root, stem):
    """The reference trainer's view of one image: its inverse depth map."""
    params = json.loads((root / "sparse" / "0" / "depth_params.json").read_text())[stem]
    png = cv2.imread(str(root / "depths" / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
    assert png is not None and png.dtype == np.uint16 and png.ndim == 2
    return png.astype(np.float64) / 2 ** 16 * params["scale"] + params["offset"], params


def _scene_with_priors(tmp_path, *, relative=False):
    model = synthetic_model()
    scene = write_scene(tmp_path, model)
    rng = np.random.default_rng(1)
    truth = {}
    for image in model.sorted_images():
        camera = model.cameras[image.camera_id]
        height, width = camera.height // 8, camera.width // 8
        depth = rng.uniform(2.0, 40.0, (height, width)).astype(np.float32)
        mask = rng.random((height, width)) > 0.2
        truth[image.name] = (depth, mask)
        if relative:  # known up to scale and shift in inverse depth; the sfm priors give the scale
            write_prior_maps(scene, "sfm", image.name, depth=depth, mask=mask & (rng.random(mask.shape) > 0.7))
            inverse = np.where(mask, 1.0 / depth, 0.0)
            relative_depth = 1.0 / (inverse * 3.0 + 0.25)
            write_prior_maps(scene, "ndn", image.name, depth=relative_depth, mask=mask, relative_depth=True)
        else:
            write_prior_maps(scene, "gt", image.name, depth=depth, mask=mask)
    return scene, truth


@pytest.mark.parametrize("relative", [False, True])
def test_export_reads_back_as_the_priors_inverse_depth(tmp_path, relative, capsys):
    scene, truth = _scene_with_priors(tmp_path, relative=relative)
    out = tmp_path / "for_3dgs"
    source = "ndn" if relative else "gt"
    assert main(["priors-export", str(scene), "--source", source, "--format", "3dgs", "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    params_all = json.loads((out / "sparse" / "0" / "depth_params.json").read_text())
    assert set(params_all) == {name.rsplit(".", 1)[0] for name in truth}
    top = max(float((1.0 / d[m]).max()) for d, m in truth.values())
    scales = []
    for name, (depth, mask) in truth.items():
        inverse, params = _read_3dgs(out, name.rsplit(".", 1)[0])
        scales.append(params["scale"])
        assert inverse.shape == depth.shape
        expected = np.where(mask, 1.0 / depth.astype(np.float64), 0.0)
        # within half a 16-bit step (+2%: the EXR holds float32 depths; a relative source's fit is exact: affine data)
        tolerance = top / (2 ** 16 - 1) * 0.51 + (1e-6 if relative else 0.0)
        np.testing.assert_allclose(inverse, expected, rtol=0, atol=tolerance)
    # one scale for all views: the reference code's median-scale window never drops one
    assert max(scales) <= 5 * np.median(scales) and min(scales) >= 0.2 * np.median(scales)


def test_export_without_priors_fails_with_exit_1(tmp_path, capsys):
    scene = write_scene(tmp_path, synthetic_model())
    assert main(["priors-export", str(scene), "--source", "gt"]) == 1


def test_priors_command_still_takes_a_scene(tmp_path):
    from esgs.core.cli import build_parser

    args = build_parser().parse_args(["priors", str(tmp_path), "--method", "sfm"])
    assert args.method == "sfm" and args.scene == tmp_path
