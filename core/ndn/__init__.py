"""NDN: the multi-view diffusion prior for depth and normals (paper section 3.3).

- :mod:`.config`: model, diffusion and training settings;
- :mod:`.model`: the two-branch UNet noise predictor conditioned on three views;
- :mod:`.diffusion`: DDPM schedule, training loss, deterministic DDIM sampling;
- :mod:`.data`: view triples from scene folders, the shard builder;
- :mod:`.train`: training with checkpoints; weights on disk;
- :mod:`.infer`: writing ``priors/ndn`` for a scene and scoring a model.

Heavy imports (torch) happen when a sub-module is imported, not here.
"""
