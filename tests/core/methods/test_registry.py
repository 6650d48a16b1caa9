"""The method registry: a new method is one module plus a registration, old run configs still load."""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import pytest
import torch

from esgs.core.config import config_to_dict
from esgs.core.errors import ConfigError
from esgs.core.methods import (DropoutGSConfig, ESGSConfig, Method, MethodParts, full_esgs, get_method,
                               load_run_config, make_trainer, method_names, register_method, train,
                               train_config_from_dict, unregister_method)
from esgs.core.train.config import TrainConfig
from esgs.core.train.hooks import RunView, TrainHook
from esgs.core.train.losses import LossContext, LossTerm
from tests.core.train.scene import make_scene


# --- a whole new method: settings, a hook, a build function, one registration ------------------
@dataclass
class OpacityPenaltyConfig:
    """Settings of the example method: an L2 penalty on the opacities."""

    opacity_penalty: float = field(default=0.5, metadata={"help": "weight of mean(opacity^2)"})

    def validate(self) -> None:
        if self.opacity_penalty < 0:
            raise ConfigError(f"opacity_penalty must be >= 0, got {self.opacity_penalty}")


class OpacityPenaltyHook(TrainHook):
    name = "opacity_penalty"

    def __init__(self, settings: OpacityPenaltyConfig):
        self.settings = settings

    def setup(self, run: RunView) -> None:
        run.add_loss_term(LossTerm("opacity_l2", self.settings.opacity_penalty, self._term))

    @staticmethod
    def _term(context: LossContext) -> torch.Tensor:
        return context.params.opacities.pow(2).mean()


def build_opacity_penalty(settings: OpacityPenaltyConfig, config: TrainConfig) -> MethodParts:
    settings.validate()
    return MethodParts(hooks=[OpacityPenaltyHook(settings)])


@pytest.fixture
def opacity_penalty_method():
    method = register_method(Method(name="opacity-penalty", label="3DGS + opacity L2",
                                    settings_class=OpacityPenaltyConfig, build=build_opacity_penalty))
    yield method
    unregister_method(method.name)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("registry") / "scene", views=6, width=32, height=24)


def _config(scene, out, **values) -> TrainConfig:
    return TrainConfig(scene=scene, out=out, iterations=30, backend="cpu", threads=1, lpips=False, test_every=3,
                       save_renders=False, checkpoint_every=0, progress_every=10, densify_until=0, **values)


def test_a_registered_method_trains_without_any_edit_of_the_trainer(scene, tmp_path, opacity_penalty_method):
    assert "opacity-penalty" in method_names()
    plain = train(_config(scene, tmp_path / "plain"))
    penalised = train(_config(scene, tmp_path / "penalised", method="opacity-penalty",
                              method_config=OpacityPenaltyConfig(opacity_penalty=5.0)))
    from esgs.core.formats.ply import read_gaussians_ply

    def mean_opacity(result) -> float:
        logits = torch.from_numpy(read_gaussians_ply(result.point_cloud).opacity_logit)
        return float(torch.sigmoid(logits).mean())

    # the penalty pulls every opacity down: the same seed without it keeps them higher
    assert mean_opacity(penalised) < 0.9 * mean_opacity(plain)
    saved = json.loads((tmp_path / "penalised" / "config.json").read_text())
    assert saved["method"] == "opacity-penalty" and saved["method_config"] == {"opacity_penalty": 5.0}
    # its config reads back typed, and the run resumes through the registry
    assert load_run_config(tmp_path / "penalised" / "config.json").method_config == OpacityPenaltyConfig(5.0)
    with pytest.raises(ConfigError, match="opacity_penalty must be"):
        make_trainer(_config(scene, tmp_path / "bad", method="opacity-penalty",
                             method_config={"opacity_penalty": -1.0}))


def test_unknown_methods_and_wrong_settings_are_clear_errors(scene, tmp_path):
    with pytest.raises(ConfigError, match="unknown training method 'nope'") as error:
        make_trainer(_config(scene, tmp_path / "a", method="nope"))
    assert "3dgs" in error.value.hint and "esgs" in error.value.hint
    with pytest.raises(ConfigError, match="takes ESGSConfig settings"):
        make_trainer(_config(scene, tmp_path / "b", method="esgs", method_config=DropoutGSConfig()))
    with pytest.raises(ConfigError, match="unknown setting"):
        make_trainer(_config(scene, tmp_path / "c", method="esgs", method_config={"depth_wieght": 2.0}))
    # the plain trainer refuses a config naming another method instead of silently training 3DGS
    from esgs.core.train.trainer import Trainer

    with pytest.raises(ConfigError, match="esgs.core.methods.train"):
        Trainer(_config(scene, tmp_path / "d", method="esgs"))
    with pytest.raises(ConfigError, match="registered already"):
        register_method(get_method("esgs"))


def test_full_esgs_is_defined_once_and_follows_the_prior_source(tmp_path):
    gt = full_esgs("gt")
    assert (gt.depth, gt.normal, gt.consistency, gt.gpdfn, gt.fused_k) == (True, True, False, True, 3)
    sfm = full_esgs("sfm")  # no normal maps: depth-normal consistency stands in for the normal prior
    assert (sfm.depth, sfm.normal, sfm.consistency) == (True, False, True)
    # with a scene, what its folder holds decides
    (tmp_path / "priors" / "labels" / "depth").mkdir(parents=True)
    assert full_esgs("labels", scene=tmp_path).normal is False
    (tmp_path / "priors" / "labels" / "normal").mkdir()
    assert full_esgs("labels", scene=tmp_path).normal is True
    assert full_esgs("gt", depth_weight=3.0, gpdfn=False).depth_weight == 3.0
    with pytest.raises(ConfigError):
        full_esgs("gt", fused_k=9)


def test_a_run_config_saved_before_methods_were_registered_still_loads(tmp_path):
    esgs_section = config_to_dict(ESGSConfig(priors="gt", depth=True, gpdfn=True))
    legacy = {**config_to_dict(TrainConfig(iterations=50)), "esgs": esgs_section,
              "baselines": {"mip_splatting": False, "dropout_gs": False, "dropout_rate": 0.1}}
    del legacy["method"], legacy["method_config"], esgs_section["sky_weight"]  # as runs from before the sky loss
    config = train_config_from_dict(legacy)
    assert config.method == "esgs" and config.method_config.depth and config.method_config.gpdfn
    assert config.method_config.sky_weight == 0.0  # runs saved before the sky loss trained without it
    legacy["esgs"] = config_to_dict(ESGSConfig())  # every part off: a 3DGS run
    legacy["baselines"] = {"mip_splatting": False, "dropout_gs": True, "dropout_rate": 0.25}
    config = train_config_from_dict(legacy)
    assert config.method == "dropout-gs" and config.method_config == DropoutGSConfig(dropout_rate=0.25)
    legacy["baselines"] = {"mip_splatting": True, "dropout_gs": True}
    with pytest.raises(ConfigError, match="combined the methods"):
        train_config_from_dict(legacy)
    legacy["baselines"] = {}
    assert train_config_from_dict(legacy).method == "3dgs"


def test_the_train_command_lists_methods_and_starts_full_esgs_from_method_esgs(tmp_path, capsys):
    import argparse

    from esgs.core.commands import train as train_command

    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    assert train_command.run(parser.parse_args(["--list-methods"])) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in ("3dgs", "esgs", "mip-splatting", "dropout-gs"))
    args = parser.parse_args(["scene", "--out", str(tmp_path), "--method", "esgs", "--priors", "sfm",
                              "--gpdfn-voxel-size", "0.5", "--no-gpdfn"])
    config = train_command.build_config(args)
    assert config.method_config == full_esgs("sfm", gpdfn=False, gpdfn_voxel_size=0.5)
    # the older spelling: component flags alone choose ESGS with only those parts on
    args = parser.parse_args(["scene", "--out", str(tmp_path), "--priors", "gt", "--depth"])
    config = train_command.build_config(args)
    assert config.method == "esgs" and config.method_config.depth and not config.method_config.gpdfn


def test_the_vanilla_switch_trains_plain_3dgs_and_refuses_clashing_flags(tmp_path):
    import argparse

    from esgs.core.commands import train as train_command
    from esgs.core.errors import ConfigError
    from esgs.core.train.config import VANILLA_3DGS, TrainConfig

    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    default = train_command.build_config(parser.parse_args(["scene", "--out", str(tmp_path)]))
    assert (default.sky, default.mask_source) == (TrainConfig.sky, TrainConfig.mask_source) == ("envmap", "auto")
    plain = train_command.build_config(parser.parse_args(["scene", "--out", str(tmp_path), "--vanilla"]))
    assert {key: getattr(plain, key) for key in VANILLA_3DGS} == VANILLA_3DGS
    assert plain.iterations == default.iterations and plain.method == "3dgs"
    # hidden Gaussians are pruned by default, never in plain 3DGS
    assert (default.prune_hidden, plain.prune_hidden) == (0.1, 0.0)
    with pytest.raises(ConfigError, match="--prune-hidden"):
        train_command.build_config(parser.parse_args(["scene", "--out", str(tmp_path), "--vanilla",
                                                      "--prune-hidden", "0.2"]))
    # a flag saying the same is fine; one saying otherwise is an error naming it
    same = parser.parse_args(["scene", "--out", str(tmp_path), "--vanilla", "--sky", "none"])
    assert train_command.build_config(same).sky == "none"
    with pytest.raises(ConfigError, match="--sky"):
        train_command.build_config(parser.parse_args(["scene", "--out", str(tmp_path), "--vanilla", "--sky", "envmap"]))
    with pytest.raises(ConfigError, match="--sky-alpha-weight"):
        train_command.build_config(parser.parse_args(["scene", "--out", str(tmp_path), "--vanilla",
                                                      "--sky-alpha-weight", "0.1"]))
    # a saved run with the sky model is not turned vanilla on resume
    from esgs.core.config import config_to_dict
    from esgs.core.formats.run_dir import RunDir
    from esgs.core.io_utils import atomic_write_json

    run = tmp_path / "run"
    run.mkdir()
    atomic_write_json(RunDir(run).config, {**config_to_dict(default), "scene": "scene", "out": str(run)})
    with pytest.raises(ConfigError, match="resumed"):
        train_command.build_config(parser.parse_args(["scene", "--out", str(run), "--resume", "--vanilla"]))
