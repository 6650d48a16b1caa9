"""Drawing the add-on's panels and preferences without a window.

:class:`RecordingLayout` stands in for a ``bpy.types.UILayout``: every call is checked
against the real UILayout's RNA (the function exists, its keywords and icon are real ones,
a property drawn exists on its data, an operator button names a registered operator) and
recorded; calls return another recording layout (``operator()`` an object that takes the
operator's properties), so a panel's whole ``draw()`` runs as in Blender.

Run as a script (``python panel_drawing.py PROFILE``), it enables the add-on the way Blender
loads an installed extension, as ``bl_ext.user_default.esgs`` from the user profile PROFILE
(whose ``extensions/user_default/esgs`` is the add-on's folder), draws everything in a few
states and prints a JSON summary on its last line (see ``test_panel_draw.py``).
"""
from __future__ import annotations

import importlib
import json
import sys
from types import ModuleType, SimpleNamespace
from typing import Any, NamedTuple

import bpy

_FUNCTIONS = bpy.types.UILayout.bl_rna.functions
_LAYOUT_PROPERTIES = {p.identifier for p in bpy.types.UILayout.bl_rna.properties}
_ICONS = {item.identifier for item in _FUNCTIONS["label"].parameters["icon"].enum_items}


class Call(NamedTuple):
    """One UILayout call: its function name, arguments and keywords."""

    name: str
    args: tuple
    kwargs: dict

    @property
    def text(self) -> str:
        """The text shown by a label, the idname of an operator, the property of a prop."""
        if self.name == "label":
            return self.kwargs.get("text", "")
        if self.name in ("operator", "prop"):
            return self.args[-1] if self.args else self.kwargs.get("operator") or self.kwargs.get("property")
        return self.kwargs.get("text", "")


def _operator_type(idname: str):
    module, _, name = idname.partition(".")
    return getattr(getattr(bpy.ops, module), name).get_rna_type()  # KeyError when not registered


class OperatorButton:
    """What ``layout.operator()`` returns: takes only the operator's own properties."""

    def __init__(self, idname: str):
        object.__setattr__(self, "_properties", {p.identifier for p in _operator_type(idname).properties})
        object.__setattr__(self, "values", {})

    def __setattr__(self, name: str, value: Any) -> None:
        assert name in self._properties, f"the operator has no property {name!r}"
        self.values[name] = value


def _check_call(name: str, args: tuple, kwargs: dict) -> None:
    parameters = [p.identifier for p in _FUNCTIONS[name].parameters]
    assert len(args) <= len(parameters), (name, args)
    assert set(kwargs) <= set(parameters), (name, sorted(set(kwargs) - set(parameters)))
    assert not set(kwargs) & set(parameters[:len(args)]), (name, "given twice", kwargs)
    if "icon" in kwargs:
        assert kwargs["icon"] in _ICONS, f"no icon {kwargs['icon']!r}"
    for key in ("text", "heading"):
        if key in kwargs:
            assert isinstance(kwargs[key], str), (name, key, kwargs[key])
    if name in ("prop", "prop_search", "prop_enum", "prop_menu_enum", "props_enum", "prop_tabs_enum"):
        data = args[0] if args else kwargs.get("data")
        prop = args[1] if len(args) > 1 else kwargs.get("property")
        assert data is not None, f"{name}() of None: the panel would draw nothing there"
        if prop.startswith('["'):
            assert prop[2:-2] in data.keys(), f"no custom property {prop}"
        elif hasattr(data, "bl_rna"):
            assert prop in data.bl_rna.properties, f"{type(data).__name__} has no property {prop!r}"
            getattr(data, prop)  # Blender reads the value to draw it (a getter or dynamic enum runs)
        else:
            assert hasattr(data, prop), prop
    if name == "operator":
        _operator_type(args[0] if args else kwargs["operator"])


class RecordingLayout:
    """A UILayout stand-in that records (into a shared list) and checks every call."""

    def __init__(self, calls: list[Call]):
        object.__setattr__(self, "calls", calls)
        object.__setattr__(self, "attributes", {})

    def __getattr__(self, name: str):
        if name not in _FUNCTIONS:
            raise AttributeError(f"UILayout has no function {name!r}")

        def call(*args, **kwargs):
            _check_call(name, args, kwargs)
            self.calls.append(Call(name, args, kwargs))
            if name == "operator":
                return OperatorButton(args[0] if args else kwargs["operator"])
            if name in ("panel", "panel_prop"):
                return RecordingLayout(self.calls), RecordingLayout(self.calls)
            return RecordingLayout(self.calls)

        return call

    def __setattr__(self, name: str, value: Any) -> None:
        assert name in _LAYOUT_PROPERTIES, f"UILayout has no property {name!r}"
        self.attributes[name] = value


class _Drawing:
    """``self`` of a draw(): the recording layout, everything else from ``source``."""

    def __init__(self, layout: RecordingLayout, source: Any):
        object.__setattr__(self, "layout", layout)
        object.__setattr__(self, "_source", source)

    def __getattr__(self, name: str):
        return getattr(self._source, name)


def panel_classes(addon: ModuleType) -> list[type]:
    """Every Panel class of the add-on's ``panels`` package, in registration order."""
    registry = importlib.import_module(f"{addon.__name__}.esgs_addon._registry")
    panels = importlib.import_module(f"{addon.__name__}.panels")
    return [cls for module in registry.feature_modules(panels) for cls in getattr(module, "CLASSES", ())
            if issubclass(cls, bpy.types.Panel)]


def draw_panel(cls: type, context: Any = None) -> tuple[bool, list[Call]]:
    """``(poll result, calls)`` of drawing panel ``cls`` (its header first, when it has one);
    the panel is drawn whatever poll says, as a check that drawing it cannot fail either way."""
    context = context or bpy.context
    shown = cls.poll(context) if "poll" in vars(cls) else True
    calls: list[Call] = []
    drawing = _Drawing(RecordingLayout(calls), cls)
    if "draw_header" in vars(cls):
        cls.draw_header(drawing, context)
    cls.draw(drawing, context)
    return bool(shown), calls


def preferences_class(addon: ModuleType) -> type:
    return importlib.import_module(f"{addon.__name__}.esgs_addon.preferences").ESGS_AP_preferences


def draw_preferences(addon: ModuleType, context: Any = None) -> list[Call]:
    """The calls of the add-on preferences' draw(): with the real preferences when the add-on
    is enabled, else with their defaults (the bpy module registers without enabling)."""
    context = context or bpy.context
    cls = preferences_class(addon)
    entry = context.preferences.addons.get(cls.bl_idname)
    source = entry.preferences if entry is not None else SimpleNamespace(**{
        p.identifier: p.default for p in cls.bl_rna.properties if p.identifier not in ("rna_type", "bl_idname")})
    calls: list[Call] = []
    cls.draw(_Drawing(RecordingLayout(calls), source), context)
    return calls


def draw_everything(addon: ModuleType, context: Any = None) -> dict[str, list[Call]]:
    """Every panel (by bl_idname) and the preferences ("preferences") drawn once."""
    drawn = {cls.bl_idname: draw_panel(cls, context)[1] for cls in panel_classes(addon)}
    drawn["preferences"] = draw_preferences(addon, context)
    return drawn


def _summary(drawn: dict[str, list[Call]]) -> dict[str, Any]:
    return {name: {"operators": [c.text for c in calls if c.name == "operator"],
                   "labels": [c.text for c in calls if c.name == "label"],
                   "props": [c.text for c in calls if c.name == "prop"]} for name, calls in drawn.items()}


def main(argv: list[str]) -> None:
    """Enable the add-on as the installed extension ``bl_ext.user_default.esgs`` and draw it."""
    import addon_utils

    module_name = "bl_ext.user_default.esgs"
    addon = addon_utils.enable(module_name, default_set=True, handle_error=None)
    assert addon is not None and addon.__name__ == module_name, addon
    settings = bpy.context.scene.esgs
    result: dict[str, Any] = {"no_scene": _summary(draw_everything(addon))}
    settings.training.scene_dir = argv[0]
    settings.training.method = "esgs"  # its prior-source drop-down lists the scene folder's priors
    result["scene_chosen"] = _summary(draw_everything(addon))
    result["prior_sources"] = [item[0] for item in importlib.import_module(
        f"{addon.__name__}.esgs_addon.settings_training").prior_source_choices(settings.training)]
    result["modules"] = sorted(name for name in sys.modules if name == "esgs" or name.startswith("esgs."))
    result["addon_id"] = preferences_class(addon).bl_idname
    result["version"] = addon.__version__
    print(json.dumps(result))


if __name__ == "__main__":
    main(sys.argv[1:])
