"""The training settings (esgs_addon/settings_training.py) derived from the engine's dataclasses,
read back by training_job.training_config, and drawn by the training panel."""
from __future__ import annotations

import dataclasses

import pytest

bpy = pytest.importorskip("bpy")

from esgs.core.errors import ConfigError
from esgs.core.methods import ESGSConfig, full_esgs, get_method, method_names
from esgs.core.train.config import TrainConfig
from esgs.esgs_addon import settings_training, training_job

from .test_panels import draw


def _properties():
    return bpy.context.scene.esgs.training.bl_rna.properties


def _derived_fields():
    """(dataclass field, its property) of every option derived from a dataclass."""
    fields = [fld for fld in dataclasses.fields(TrainConfig) if fld.name in settings_training.TRAIN_FIELDS]
    for _, settings_class in settings_training.method_settings_classes():
        fields += [fld for fld in dataclasses.fields(settings_class) if fld.type in ("bool", "int", "float", "str")]
    return [(fld, _properties()[fld.name]) for fld in fields]


def test_every_option_has_its_dataclass_fields_default_and_help():
    derived = _derived_fields()
    assert {fld.name for fld, _ in derived} >= {"iterations", "width", "seed", "backend", "priors", "depth", "normal",
                                               "consistency", "gpdfn", "depth_weight", "fused_k", "mip_filter_3d",
                                               "dropout_rate"}
    for fld, prop in derived:
        # the panel's own words where the dataclass's speak of command-line flags
        help_text = settings_training._TRAIN_EXTRA.get(fld.name, {}).get("description", fld.metadata["help"])
        assert prop.description == help_text, fld.name
        assert "--" not in prop.description, fld.name
        default = prop.default
        if fld.name == "iterations":
            assert default == settings_training.DEFAULT_ITERATIONS < fld.default  # minutes on a CPU, not hours
            continue
        if prop.type == "FLOAT":
            assert default == pytest.approx(fld.default, rel=1e-6), fld.name
        else:
            assert default == fld.default, fld.name
        if "choices" in fld.metadata:
            assert prop.type == "ENUM" and [item.identifier for item in prop.enum_items] == list(fld.metadata["choices"])
    method = _properties()["method"]
    assert [item.identifier for item in method.enum_items] == list(method_names())
    assert [item.name for item in method.enum_items] == [get_method(name).label for name in method_names()]
    assert method.description == settings_training.METHOD_DESCRIPTION and "--" not in method.description


def test_a_fresh_scene_trains_plain_3dgs_with_the_trainers_defaults():
    config = training_job.training_config(bpy.context.scene.esgs.training)
    assert (config.method, config.method_config) == ("3dgs", None)
    for name in settings_training.TRAIN_FIELDS:
        expected = settings_training.DEFAULT_ITERATIONS if name == "iterations" else getattr(TrainConfig(), name)
        assert getattr(config, name) == expected, name  # floats come back exactly


def _other_value(fld: dataclasses.Field, prop):
    if prop.type == "BOOLEAN":
        return not fld.default
    if prop.type == "ENUM":
        return next(item.identifier for item in prop.enum_items if item.identifier != fld.default)
    if prop.type == "STRING":
        return "sfm"  # the one string option: ESGS's prior source
    return fld.default + (2 if fld.name == "fused_k" else 1) if prop.type == "INT" else fld.default + 0.25


@pytest.mark.parametrize("method", [name for name, _ in settings_training.method_settings_classes()])
def test_options_round_trip_through_training_config(method):
    settings = bpy.context.scene.esgs.training
    settings.method = method
    settings_class = get_method(method).settings_class
    expected = {}
    # the prior source first: choosing one with every ESGS part off fills in the full method
    for fld, prop in sorted(_derived_fields(), key=lambda pair: pair[0].name != "priors"):
        if fld.name in settings_training.TRAIN_FIELDS or any(f.name == fld.name for f in
                                                             dataclasses.fields(settings_class)):
            expected[fld.name] = _other_value(fld, prop)
            setattr(settings, fld.name, expected[fld.name])
    config = training_job.training_config(settings)
    assert config.method == method and isinstance(config.method_config, settings_class)
    for name, value in expected.items():
        holder = config if name in settings_training.TRAIN_FIELDS else config.method_config
        assert getattr(holder, name) == value, name  # exact: the float32 storage is rounded back


def test_esgs_with_a_prior_source_is_the_full_method():
    settings = bpy.context.scene.esgs.training
    settings.method = "esgs"
    config = training_job.training_config(settings)
    # chosen with nothing set: the full method on the default source, as `esgs train --esgs`
    assert settings.priors == settings_training.DEFAULT_PRIOR_SOURCE == "auto"
    assert config.method_config == full_esgs("auto") == full_esgs()
    # another source while the settings are still the filled-in full method: that source's
    # full method (its own depth weight), as `esgs train --method esgs --priors ndn`
    settings.prior_source = "ndn"
    assert training_job.training_config(settings).method_config == full_esgs("ndn") != full_esgs("auto")
    settings.prior_source = "NONE"
    for part in settings_training.ESGS_PARTS:
        setattr(settings, part, False)
    settings.depth_weight = ESGSConfig.depth_weight
    assert training_job.training_config(settings).method_config == ESGSConfig()  # nothing switched on
    settings.priors = "sfm"
    assert training_job.training_config(settings).method_config == full_esgs("sfm")
    # once a part is chosen by hand, another source does not reset the parts
    settings.gpdfn = False
    settings.priors = "gt"
    config = training_job.training_config(settings)
    assert (config.method_config.gpdfn, config.method_config.priors) == (False, "gt")
    # nor does choosing ESGS again
    settings.method = "mip-splatting"
    settings.method = "esgs"
    assert (settings.gpdfn, settings.priors) == (False, "gt")


def test_3dgs_chosen_after_esgs_trains_3dgs():
    settings = bpy.context.scene.esgs.training
    settings.method = "esgs"  # fills in the auto source and the full method
    settings.method = "3dgs"
    config = training_job.training_config(settings)
    assert (config.method, config.method_config) == ("3dgs", None)
    # a scene (or script) from before the method selector: a source or a part alone chose ESGS
    bpy.context.scene.esgs.property_unset("training")
    settings = bpy.context.scene.esgs.training
    settings.depth, settings.priors = True, "sfm"
    assert not settings.is_property_set("method")
    assert training_job.training_config(settings).method == "esgs"


def test_an_unknown_prior_source_is_a_config_error():
    settings = bpy.context.scene.esgs.training
    settings.depth, settings.priors = True, "gtt"
    with pytest.raises(ConfigError, match="unknown prior source 'gtt'"):
        training_job.training_config(settings)


def test_the_panel_draws_the_chosen_methods_settings():
    from esgs.panels.training_panel import ESGS_PT_training

    settings = bpy.context.scene.esgs.training
    props = lambda record: [entry[1] for entry in record if entry[0] == "prop"]
    shown = props(draw(ESGS_PT_training))
    assert {"method", "iterations", "width", "seed", "backend"} <= set(shown)
    assert not {"priors", "depth", "gpdfn", "mip_filter_3d"} & set(shown)  # plain 3DGS: no method settings
    assert ("operator", "esgs.compute_priors") in draw(ESGS_PT_training)  # priors also give plain runs sky masks

    settings.method = "esgs"
    record = draw(ESGS_PT_training)
    assert {"prior_source", *settings_training.ESGS_PARTS} <= set(props(record))
    assert "priors" not in props(record)  # the stored string is not typed in: a drop-down sets it
    assert {"depth_weight", "normal_weight"} <= set(props(record))  # the full method on auto: its parts' weights
    settings.prior_source = "NONE"
    settings.depth = settings.normal = False
    record = draw(ESGS_PT_training)
    assert "depth_weight" not in props(record)  # a weight shows beside its switched-on part
    assert ("label", "Choose a prior source for the full method") in record
    settings.depth = True
    settings.priors = "gt"
    assert {"depth_weight"} <= set(props(draw(ESGS_PT_training)))

    settings.method = "mip-splatting"
    shown = props(draw(ESGS_PT_training))
    assert {"mip_filter_3d", "mip_filter_2d", "mip_frustum_margin"} <= set(shown) and "depth" not in shown

    # PGSR and Scaffold-GS are offered, and each draws every one of its settings under its label, none of the other's
    offered = [item.identifier for item in _properties()["method"].enum_items]
    for method, other in (("pgsr", "scaffold-gs"), ("scaffold-gs", "pgsr")):
        assert method in offered
        settings.method = method
        record = draw(ESGS_PT_training)
        own = {fld.name for fld in dataclasses.fields(get_method(method).settings_class)}
        others = {fld.name for fld in dataclasses.fields(get_method(other).settings_class)}
        assert ("label", get_method(method).label) in record
        assert own <= set(props(record)) and not others & set(props(record)), method
        assert not {"depth", "mip_filter_3d", "dropout_rate"} & set(props(record)), method


def test_the_prior_source_offers_what_the_scene_folder_holds(tmp_path):
    from esgs.panels.training_panel import ESGS_PT_training

    settings = bpy.context.scene.esgs.training
    settings.method = "esgs"
    offered = lambda: {identifier: name for identifier, name, _ in settings_training.prior_source_choices(settings)}
    # no scene folder yet: none, auto (made before training: the default), or one that Compute Priors will make
    assert offered() == {"NONE": "None", "auto": "auto (made before training)", "ndn": "ndn (compute first)",
                         "sfm": "sfm (compute first)"}
    assert settings.priors == "auto" and settings.prior_source == "auto"  # choosing ESGS chose auto
    descriptions = {identifier: text for identifier, _, text in settings_training.prior_source_choices(settings)}
    assert descriptions["auto"].startswith("Auto: best of stereo labels, NDN and SfM per pixel")
    with pytest.raises(TypeError):
        settings.prior_source = "gt"

    scene = tmp_path / "scene"
    for folder in ("priors/labels/normal", "priors/gt/depth", "priors/empty", "sparse/0", "images"):
        (scene / folder).mkdir(parents=True)
    settings.scene_dir = str(scene)
    assert offered() == {"NONE": "None", "auto": "auto (made before training)", "gt": "gt", "labels": "labels",
                         "ndn": "ndn (compute first)", "sfm": "sfm (compute first)"}  # folders with maps, most faithful first
    assert list(offered()) == ["NONE", "auto", "gt", "labels", "ndn", "sfm"]
    labels = [entry[1] for entry in draw(ESGS_PT_training) if entry[0] == "label"]
    assert "No auto priors yet: Train computes them first" in labels  # not an error: training makes them
    (scene / "priors" / "auto" / "depth").mkdir(parents=True)
    assert list(offered())[:2] == ["NONE", "auto"] and offered()["auto"] == "auto"  # the default stays first
    assert not any(entry[1].startswith("No auto priors") for entry in draw(ESGS_PT_training) if entry[0] == "label")
    (scene / "priors" / "auto" / "depth").rmdir()
    settings.prior_source = "NONE"
    for part in settings_training.ESGS_PARTS:
        setattr(settings, part, False)
    settings.prior_source = "labels"
    assert (settings.priors, settings.prior_source) == ("labels", "labels")
    assert settings.depth and settings.gpdfn  # a source chosen with every part off: the full method
    settings.prior_source = "NONE"
    assert (settings.priors, settings.prior_source) == ("", "NONE")

    # a source not computed yet is offered and makes Compute Priors compute it
    bpy.context.scene.esgs.priors.method = "ndn"
    settings.prior_source = "sfm"
    assert settings.priors == "sfm" and bpy.context.scene.esgs.priors.method == "sfm"
    labels = [entry[1] for entry in draw(ESGS_PT_training) if entry[0] == "label"]
    assert "No sfm priors yet: press Compute Priors (sfm)" in labels
    (scene / "priors" / "sfm" / "depth").mkdir(parents=True)
    assert offered()["sfm"] == "sfm"
    assert not any(entry[1].startswith("No sfm priors") for entry in draw(ESGS_PT_training) if entry[0] == "label")

    # a source set by a script (or an older .blend) whose folder is gone stays shown, marked
    settings.priors = "gt"
    (scene / "priors" / "gt" / "depth").rmdir()
    assert offered()["gt"] == "gt (missing)" and settings.prior_source == "gt"
    labels = [entry[1] for entry in draw(ESGS_PT_training) if entry[0] == "label"]
    assert "The scene folder has no gt priors: choose another source" in labels
