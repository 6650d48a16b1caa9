"""The NDN noise predictor: a small two-branch UNet conditioned on three neighbouring views.

Inputs (working resolution H x W, both multiples of ``2 ** (levels - 1)``):

- ``views`` [B, 9, H, W]: the reference view and its two nearest neighbours, RGB each, in
  [-1, 1] (channels 0-2 are the reference view);
- ``depth_state`` [B, 1, H, W]: the noisy relative-depth state x_t of the depth branch;
- ``normal_state`` [B, 3, H, W]: the noisy camera-frame normal state of the normal branch;
- ``timesteps`` [B] (int): the diffusion step t of each sample.

- ``evidence`` [B, 4, H, W] (only with ``config.evidence``; None = no evidence): the reference
  view's SfM and stereo depth as log states with their validity (:mod:`.evidence`).

Outputs: ``(depth_out [B, 1, H, W], normal_out [B, 3, H, W])``, the predicted noise (or v,
or the clean maps for the regression variant); with ``config.sky`` a third output, the sky
logit [B, 1, H, W] (a side output of the depth branch, never noised).

How the paper's description is read here (section 3.3, our interpretation):

- one encoder with shared weights embeds each of the three views; per level, the three
  feature maps are fused by a 1x1 convolution into a *multi-view context* map;
- depth branch: the 1-channel depth state is copied to 3 channels and stacked with the
  reference image, so the down-sampling path sees noise and image together; the
  up-sampling path fuses the multi-view context at every level (the paper's "fused with
  inter-frame context in the upsampling stage"). The state stays 1-channel, so the
  predicted noise is 1-channel and matches its target exactly;
- normal branch: its state is fused with the reference view's coarsest image features at
  the bottleneck at every step (coarse normals). Full-resolution image features (the
  reference view's encoder features at the finer levels) enter the up-sampling path only
  when ``t < refine_below``: the noisiest N of the T steps give coarse normals, the last
  T - N refine them with image detail. Normals are 3-vectors, so their state has 3
  channels (the paper mentions single-channel noise; a unit normal cannot live in one).
"""
from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from .config import NDNModelConfig
from .evidence import EVIDENCE_CHANNELS


def timestep_embedding(timesteps: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding of integer steps: ``timesteps`` [B] -> [B, dim]."""
    half = dim // 2
    frequencies = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=timesteps.device) / half)
    angles = timesteps.float()[:, None] * frequencies[None, :]
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=1)


def _groups(channels: int) -> int:
    return 8 if channels % 8 == 0 else 4 if channels % 4 == 0 else 1


class ResidualBlock(nn.Module):
    """Two 3x3 convolutions with group norm and SiLU; the time embedding shifts the features."""

    def __init__(self, in_channels: int, out_channels: int, time_dim: int | None):
        super().__init__()
        self.norm1 = nn.GroupNorm(_groups(in_channels), in_channels)
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.time = nn.Linear(time_dim, out_channels) if time_dim else None
        self.norm2 = nn.GroupNorm(_groups(out_channels), out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1)
        self.skip = nn.Conv2d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: torch.Tensor, time_embedding: torch.Tensor | None = None) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        if self.time is not None and time_embedding is not None:
            h = h + self.time(time_embedding)[:, :, None, None]
        h = self.conv2(F.silu(self.norm2(h)))
        return h + self.skip(x)


class ViewEncoder(nn.Module):
    """Shared image encoder: [B, 3, H, W] -> one feature map per level (channels[s] at H / 2**s)."""

    def __init__(self, channels: list[int]):
        super().__init__()
        self.stem = nn.Conv2d(3, channels[0], 3, padding=1)
        self.blocks = nn.ModuleList()
        self.downs = nn.ModuleList()
        for level, width in enumerate(channels):
            previous = channels[max(level - 1, 0)]
            self.blocks.append(ResidualBlock(previous, width, None))
            if level < len(channels) - 1:
                self.downs.append(nn.Conv2d(width, width, 3, stride=2, padding=1))

    def forward(self, image: torch.Tensor) -> list[torch.Tensor]:
        h = self.stem(image)
        features = []
        for level, block in enumerate(self.blocks):
            h = block(h)
            features.append(h)
            if level < len(self.downs):
                h = self.downs[level](h)
        return features


class BranchUNet(nn.Module):
    """A time-conditioned UNet over one diffusion state with extra features at each level.

    ``extra_channels[s]`` features are concatenated at level ``s`` of the up-sampling path
    (and at the bottleneck for the coarsest level).
    """

    def __init__(self, in_channels: int, out_channels: int, channels: list[int], extra_channels: list[int],
                 time_dim: int):
        super().__init__()
        self.input = nn.Conv2d(in_channels, channels[0], 3, padding=1)
        self.down_blocks = nn.ModuleList()
        self.downs = nn.ModuleList()
        for level, width in enumerate(channels):
            self.down_blocks.append(ResidualBlock(channels[max(level - 1, 0)], width, time_dim))
            if level < len(channels) - 1:
                self.downs.append(nn.Conv2d(width, width, 3, stride=2, padding=1))
        last = len(channels) - 1
        self.middle = ResidualBlock(channels[last] + extra_channels[last], channels[last], time_dim)
        self.up_blocks = nn.ModuleList()
        for level in range(last - 1, -1, -1):
            self.up_blocks.append(ResidualBlock(channels[level + 1] + channels[level] + extra_channels[level],
                                                channels[level], time_dim))
        self.output_norm = nn.GroupNorm(_groups(channels[0]), channels[0])
        self.output = nn.Conv2d(channels[0], out_channels, 3, padding=1)
        nn.init.zeros_(self.output.weight)  # start by predicting zero: a stable first step
        nn.init.zeros_(self.output.bias)

    def forward(self, x: torch.Tensor, time_embedding: torch.Tensor, extras: list[torch.Tensor]) -> torch.Tensor:
        h = self.input(x)
        skips = []
        for level, block in enumerate(self.down_blocks):
            h = block(h, time_embedding)
            skips.append(h)
            if level < len(self.downs):
                h = self.downs[level](h)
        last = len(self.down_blocks) - 1
        h = self.middle(torch.cat([h, extras[last]], dim=1), time_embedding)
        for index, level in enumerate(range(last - 1, -1, -1)):
            h = F.interpolate(h, size=skips[level].shape[-2:], mode="nearest")
            h = self.up_blocks[index](torch.cat([h, skips[level], extras[level]], dim=1), time_embedding)
        return self.output(F.silu(self.output_norm(h)))


class NDNUNet(nn.Module):
    """Depth and normal noise predictor conditioned on three views (see the module docstring)."""

    def __init__(self, config: NDNModelConfig | None = None, refine_below: int = 500):
        super().__init__()
        self.config = config or NDNModelConfig()
        self.config.validate()
        self.refine_below = int(refine_below)
        channels = [self.config.base_channels * 2 ** level for level in range(self.config.levels)]
        self.channels = channels
        time_dim = self.config.time_dim
        self.time_mlp = nn.Sequential(nn.Linear(time_dim, time_dim), nn.SiLU(), nn.Linear(time_dim, time_dim))
        self.encoder = ViewEncoder(channels)
        self.context = nn.ModuleList(nn.Conv2d(3 * width, width, 1) for width in channels)
        # evidence (when read) enters both branches beside their states; the sky logit is a second
        # output channel of the depth branch
        evidence = EVIDENCE_CHANNELS if self.config.evidence else 0
        self.depth_branch = BranchUNet(3 + 3 + evidence, 1 + int(self.config.sky), channels, channels, time_dim)
        self.normal_branch = BranchUNet(3 + evidence, 3, channels, channels, time_dim)

    def forward(self, views: torch.Tensor, depth_state: torch.Tensor, normal_state: torch.Tensor,
                timesteps: torch.Tensor, evidence: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        batch = views.shape[0]
        multiple = 2 ** (len(self.channels) - 1)
        if views.shape[1] != 9 or views.shape[-1] % multiple or views.shape[-2] % multiple:
            raise ValueError(f"views must be [B, 9, H, W] with H, W multiples of {multiple}, got {tuple(views.shape)}")
        time_embedding = self.time_mlp(timestep_embedding(timesteps, self.config.time_dim))
        stacked = views.reshape(batch * 3, 3, *views.shape[-2:])
        per_view = self.encoder(stacked)  # each [3B, C, h, w]
        context, reference = [], []
        for level, features in enumerate(per_view):
            grouped = features.reshape(batch, 3 * features.shape[1], *features.shape[-2:])
            context.append(self.context[level](grouped))
            reference.append(features.reshape(batch, 3, features.shape[1], *features.shape[-2:])[:, 0])
        depth_input = [views[:, :3], depth_state.expand(-1, 3, -1, -1)]
        normal_input = [normal_state]
        if self.config.evidence:
            if evidence is None:
                evidence = views.new_zeros((batch, EVIDENCE_CHANNELS, *views.shape[-2:]))
            depth_input.append(evidence)
            normal_input.append(evidence)
        elif evidence is not None:
            raise ValueError("this network was built without evidence inputs (NDNModelConfig.evidence is off)")
        depth_out = self.depth_branch(torch.cat(depth_input, dim=1), time_embedding, context)
        fine = (timesteps < self.refine_below).to(views.dtype)[:, None, None, None]
        last = len(reference) - 1
        normal_extras = [reference[level] * fine if level < last else reference[level] for level in range(len(reference))]
        normal_out = self.normal_branch(torch.cat(normal_input, dim=1), time_embedding, normal_extras)
        if self.config.sky:
            return depth_out[:, :1], normal_out, depth_out[:, 1:]
        return depth_out, normal_out


def parameter_count(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
