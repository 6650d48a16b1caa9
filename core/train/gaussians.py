"""The Gaussian model: raw (unconstrained) parameters and their activations.

Storage follows 3DGS so the PLY round trip is lossless:

- ``means``: [N, 3] world positions;
- ``sh_dc``: [N, 1, 3] degree-0 SH coefficients, ``sh_rest``: [N, K-1, 3] the higher
  bands, K = (max degree + 1)^2;
- ``opacity_logit``: [N] (opacity = sigmoid);
- ``log_scales``: [N, 3] (scale = exp);
- ``quats``: [N, 4] unnormalised (w, x, y, z) (rotation = normalised quaternion).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from ..render.sh import SHCoefficients

#: Degree-0 real SH constant: colour = SH_C0 * dc + 0.5 (the rasterizer adds the 0.5).
SH_C0 = 0.28209479177387814

#: The per-Gaussian tensors, in the order the optimizer groups and checkpoints use.
PARAMETER_NAMES = ("means", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats")


def num_sh_coefficients(degree: int) -> int:
    """K = (degree + 1)^2 coefficients per colour channel."""
    return (degree + 1) ** 2


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """[..., 3] colours in [0, 1] -> degree-0 coefficients that render as that colour."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    return dc * SH_C0 + 0.5


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    return torch.log(x / (1.0 - x))


@dataclass
class RenderParams:
    """Activated parameters handed to the rasterizer. Hooks may replace any field.

    means [N, 3], quats [N, 4] unit wxyz, scales [N, 3], opacities [N], colors the SH
    coefficients: :class:`~esgs.core.render.sh.SHCoefficients` (the model's ``sh_dc`` and
    ``sh_rest`` as they are, from :meth:`GaussianModel.render_params`) or one [N, K, 3] tensor
    (a hook's own, e.g. Scaffold-GS's decoded colours); ``sh_degree`` the active degree,
    ``extra`` [N, E] optional channels.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor | SHCoefficients
    sh_degree: int
    extra: Optional[torch.Tensor] = None


@dataclass
class GaussianModel:
    """Per-Gaussian parameters as leaf tensors (``nn.Parameter``) plus the maximum SH degree."""

    params: dict[str, torch.nn.Parameter] = field(default_factory=dict)
    max_sh_degree: int = 3

    # --- construction --------------------------------------------------------------
    @staticmethod
    def from_tensors(means: torch.Tensor, sh_dc: torch.Tensor, sh_rest: torch.Tensor, opacity_logit: torch.Tensor,
                     log_scales: torch.Tensor, quats: torch.Tensor, max_sh_degree: int) -> "GaussianModel":
        tensors = dict(means=means, sh_dc=sh_dc, sh_rest=sh_rest, opacity_logit=opacity_logit,
                       log_scales=log_scales, quats=quats)
        params = {name: torch.nn.Parameter(tensors[name].detach().to(torch.float32).contiguous())
                  for name in PARAMETER_NAMES}
        model = GaussianModel(params, max_sh_degree)
        model.check_shapes()
        return model

    @staticmethod
    def from_points(xyz: np.ndarray, rgb: np.ndarray, *, max_sh_degree: int = 3, init_opacity: float = 0.1,
                    neighbours: int = 3) -> "GaussianModel":
        """Gaussians at points ``xyz`` [P, 3] with colours ``rgb`` [P, 3] in [0, 1].

        Isotropic scale = mean distance to the ``neighbours`` nearest other points (a
        cKDTree query; duplicates get a tiny floor so log stays finite), identity rotation,
        opacity ``init_opacity``, SH bands above 0 zero.
        """
        from scipy.spatial import cKDTree

        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        count = xyz.shape[0]
        if count == 0:
            raise ValueError("from_points needs at least one point")
        k = min(neighbours, count - 1)
        if k > 0:
            distances, _ = cKDTree(xyz).query(xyz, k=k + 1)  # the first neighbour is the point itself
            mean_distance = np.asarray(distances, dtype=np.float64).reshape(count, k + 1)[:, 1:].mean(axis=1)
        else:
            mean_distance = np.full(count, 0.01)
        positive = mean_distance[mean_distance > 0]
        floor = max(float(positive.min()) * 0.1, 1e-7) if positive.size else 1e-3
        mean_distance = np.maximum(mean_distance, floor)
        means = torch.from_numpy(xyz).float()
        colours = torch.from_numpy(np.asarray(rgb, dtype=np.float64).reshape(-1, 3)).float().clamp(0.0, 1.0)
        rest = num_sh_coefficients(max_sh_degree) - 1
        quats = torch.zeros(count, 4)
        quats[:, 0] = 1.0
        return GaussianModel.from_tensors(
            means=means,
            sh_dc=rgb_to_sh_dc(colours)[:, None, :],
            sh_rest=torch.zeros(count, rest, 3),
            opacity_logit=inverse_sigmoid(torch.full((count,), float(init_opacity))),
            log_scales=torch.from_numpy(np.log(mean_distance)).float()[:, None].repeat(1, 3),
            quats=quats,
            max_sh_degree=max_sh_degree,
        )

    @staticmethod
    def random(count: int, center: np.ndarray, half_size: float, generator: np.random.Generator, **kwargs) -> "GaussianModel":
        """``count`` Gaussians uniform in a cube (``center`` ± ``half_size``) with random colours."""
        xyz = np.asarray(center, dtype=np.float64) + generator.uniform(-half_size, half_size, size=(count, 3))
        rgb = generator.uniform(0.0, 1.0, size=(count, 3))
        return GaussianModel.from_points(xyz, rgb, **kwargs)

    def check_shapes(self) -> None:
        count = self.params["means"].shape[0]
        expected = {
            "means": (count, 3), "sh_dc": (count, 1, 3),
            "sh_rest": (count, num_sh_coefficients(self.max_sh_degree) - 1, 3),
            "opacity_logit": (count,), "log_scales": (count, 3), "quats": (count, 4),
        }
        for name, shape in expected.items():
            if tuple(self.params[name].shape) != shape:
                raise ValueError(f"Gaussian parameter {name} has shape {tuple(self.params[name].shape)}, expected {shape}")

    # --- access --------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    def __getattr__(self, name: str) -> torch.nn.Parameter:
        # only called when normal lookup fails: expose parameters as attributes (model.means)
        params = self.__dict__.get("params")
        if params is not None and name in params:
            return params[name]
        raise AttributeError(name)

    def to(self, device: torch.device | str) -> "GaussianModel":
        self.params = {name: torch.nn.Parameter(p.detach().to(device)) for name, p in self.params.items()}
        return self

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    def opacities(self) -> torch.Tensor:
        """[N] activated opacity."""
        return torch.sigmoid(self.params["opacity_logit"])

    def scales(self) -> torch.Tensor:
        """[N, 3] activated scale."""
        return torch.exp(self.params["log_scales"])

    def unit_quats(self) -> torch.Tensor:
        """[N, 4] normalised wxyz rotation."""
        return torch.nn.functional.normalize(self.params["quats"], dim=-1)

    def sh_coefficients(self) -> torch.Tensor:
        """[N, K, 3] all SH coefficients."""
        return torch.cat([self.params["sh_dc"], self.params["sh_rest"]], dim=1)

    def render_params(self, sh_degree: int) -> RenderParams:
        """Activated parameters (differentiable w.r.t. the raw ones) for the rasterizer."""
        return RenderParams(means=self.params["means"], quats=self.unit_quats(), scales=self.scales(),
                            opacities=self.opacities(), colors=SHCoefficients(self.params["sh_dc"], self.params["sh_rest"]),
                            sh_degree=sh_degree)

    def set_params(self, new: dict[str, torch.nn.Parameter]) -> None:
        self.params.update(new)

    def all_finite(self) -> bool:
        return all(bool(torch.isfinite(p).all()) for p in self.params.values())

    # --- persistence ---------------------------------------------------------------
    def state_dict(self, copy: bool = True) -> dict:
        """The SH degree and every parameter (detached, on the CPU). ``copy``: cloned, so the
        state outlives later training steps (a model copy: ``from_state_dict(state_dict())``);
        ``copy=False`` shares the CPU parameters' memory, for a state written out at once (a
        checkpoint: a clone there cost one more copy of the model near the run's peak)."""
        def value(parameter: torch.Tensor) -> torch.Tensor:
            tensor = parameter.detach().cpu()
            return tensor.clone() if copy and tensor.data_ptr() == parameter.data_ptr() else tensor

        return {"max_sh_degree": self.max_sh_degree, "params": {name: value(p) for name, p in self.params.items()}}

    @staticmethod
    def from_state_dict(state: dict) -> "GaussianModel":
        return GaussianModel.from_tensors(**state["params"], max_sh_degree=int(state["max_sh_degree"]))

    def to_ply(self):
        """The model as :class:`esgs.core.formats.ply.GaussianPly` (standard 3DGS PLY fields)."""
        from ..formats.ply import GaussianPly

        def array(name: str) -> np.ndarray:
            # float32 parameters are shared, not copied: the PLY writer converts a block at a time
            return self.params[name].detach().cpu().numpy().astype(np.float32, copy=False)

        count = len(self)
        return GaussianPly(
            means=array("means"), normals=np.zeros((count, 3), np.float32), sh_dc=array("sh_dc")[:, 0, :],
            sh_rest=array("sh_rest"), opacity_logit=array("opacity_logit"), log_scales=array("log_scales"),
            quats_wxyz=array("quats"),
        )

    @staticmethod
    def from_ply(ply) -> "GaussianModel":
        """Build a model from a :class:`esgs.core.formats.ply.GaussianPly`."""
        sh_rest = np.asarray(ply.sh_rest, dtype=np.float32)
        count = np.asarray(ply.means).shape[0]
        if sh_rest.ndim != 3:
            sh_rest = sh_rest.reshape(count, -1, 3)
        degree = int(round(np.sqrt(sh_rest.shape[1] + 1))) - 1
        return GaussianModel.from_tensors(
            means=torch.from_numpy(np.asarray(ply.means, np.float32)),
            sh_dc=torch.from_numpy(np.asarray(ply.sh_dc, np.float32)).reshape(count, 1, 3),
            sh_rest=torch.from_numpy(sh_rest),
            opacity_logit=torch.from_numpy(np.asarray(ply.opacity_logit, np.float32)).reshape(count),
            log_scales=torch.from_numpy(np.asarray(ply.log_scales, np.float32)),
            quats=torch.from_numpy(np.asarray(ply.quats_wxyz, np.float32)),
            max_sh_degree=degree,
        )
