"""The geometry-node tree and material that display imported Gaussians.

The object keeps every Gaussian; what is shown is decided by the node group's inputs on
the object's modifier, so it can be changed after import without re-reading the file:

- ``Ellipsoids``: points (spheres of ``Point Radius``) or one ico sphere per Gaussian,
  scaled by its ``scale`` attribute times ``Ellipsoid Size`` (in standard deviations) and
  rotated by its ``rotation`` quaternion;
- ``Opacity Min``: Gaussians below this activated opacity are hidden;
- ``Max Display``: at most about this many Gaussians are shown (a seeded random subset);
- ``Heat Map`` with ``Distance Min`` / ``Distance Max``: colour by the ``distance``
  attribute (blue -> red) instead of the Gaussians' own colour.

The tree writes ``display_color`` and ``display_alpha``, which the material reads (on the
points themselves and on ellipsoid instances).
"""
from __future__ import annotations

from typing import Any

import bpy

GROUP_NAME = "ESGS Gaussians"
MATERIAL_NAME = "ESGS Gaussian"
MODIFIER_NAME = "ESGS Gaussians"
#: bump when the tree changes: an older group in a saved file is rebuilt
TREE_VERSION = 1

DISPLAY_COLOR = "display_color"
DISPLAY_ALPHA = "display_alpha"

#: (name, socket type, default, min, max, description) of the modifier inputs
INPUTS: tuple[tuple[str, str, Any, Any, Any, str], ...] = (
    ("Ellipsoids", "NodeSocketBool", False, None, None, "Show each Gaussian as an ellipsoid instead of a point"),
    ("Opacity Min", "NodeSocketFloat", 0.0, 0.0, 1.0, "Hide Gaussians whose opacity is below this"),
    ("Max Display", "NodeSocketInt", 1_000_000, 0, 2**31 - 1, "Show at most about this many Gaussians"),
    ("Point Radius", "NodeSocketFloat", 0.01, 0.0, None, "Radius of the points, in scene units"),
    ("Ellipsoid Size", "NodeSocketFloat", 2.0, 0.0, None, "Ellipsoid half-axes in standard deviations"),
    ("Heat Map", "NodeSocketBool", False, None, None, "Colour by the distance attribute (blue near, red far)"),
    ("Distance Min", "NodeSocketFloat", 0.0, 0.0, None, "Distance shown in blue"),
    ("Distance Max", "NodeSocketFloat", 0.1, 0.0, None, "Distance shown in red (and beyond)"),
    ("Seed", "NodeSocketInt", 0, 0, None, "Seed of the random subset shown under Max Display"),
)

#: blue -> cyan -> green -> yellow -> red, the usual distance colour scale
HEAT_COLOURS = ((0.0, (0.0, 0.0, 1.0, 1.0)), (0.25, (0.0, 1.0, 1.0, 1.0)), (0.5, (0.0, 1.0, 0.0, 1.0)),
                (0.75, (1.0, 1.0, 0.0, 1.0)), (1.0, (1.0, 0.0, 0.0, 1.0)))


def _socket(sockets, name: str):
    """The first enabled socket called ``name`` (nodes keep disabled ones for other types)."""
    for socket in sockets:
        if socket.name == name and getattr(socket, "enabled", True):
            return socket
    raise KeyError(f"no enabled socket {name!r}")


def gaussian_material() -> bpy.types.Material:
    """The shared material: emission of ``display_color`` with ``display_alpha`` transparency."""
    material = bpy.data.materials.get(MATERIAL_NAME)
    if material is not None and material.get("esgs_version") == TREE_VERSION:
        return material
    if material is None:
        material = bpy.data.materials.new(MATERIAL_NAME)
    material["esgs_version"] = TREE_VERSION
    tree = material.node_tree
    tree.nodes.clear()
    nodes, links = tree.nodes, tree.links

    # Points carry the attributes themselves; ellipsoid instances carry them on the
    # instance. An attribute missing from one place reads as zero, so the sum is the value.
    def attribute(name: str, kind: str, y: float):
        node = nodes.new("ShaderNodeAttribute")
        node.attribute_type = kind
        node.attribute_name = name
        node.location = (-700, y)
        return node

    colour_add = nodes.new("ShaderNodeMix")
    colour_add.data_type = "RGBA"
    colour_add.blend_type = "ADD"
    colour_add.location = (-450, 200)
    _socket(colour_add.inputs, "Factor").default_value = 1.0
    links.new(attribute(DISPLAY_COLOR, "GEOMETRY", 300).outputs["Color"], _socket(colour_add.inputs, "A"))
    links.new(attribute(DISPLAY_COLOR, "INSTANCER", 100).outputs["Color"], _socket(colour_add.inputs, "B"))
    alpha_add = nodes.new("ShaderNodeMath")
    alpha_add.operation = "ADD"
    alpha_add.use_clamp = True
    alpha_add.location = (-450, -150)
    links.new(attribute(DISPLAY_ALPHA, "GEOMETRY", -100).outputs["Fac"], alpha_add.inputs[0])
    links.new(attribute(DISPLAY_ALPHA, "INSTANCER", -300).outputs["Fac"], alpha_add.inputs[1])

    # emission: Gaussian colours are observed radiance, lighting them again would darken them
    emission = nodes.new("ShaderNodeEmission")
    emission.location = (-200, 150)
    links.new(_socket(colour_add.outputs, "Result"), emission.inputs["Color"])
    transparent = nodes.new("ShaderNodeBsdfTransparent")
    transparent.location = (-200, 0)
    mix = nodes.new("ShaderNodeMixShader")
    mix.location = (50, 100)
    links.new(alpha_add.outputs[0], mix.inputs["Fac"])
    links.new(transparent.outputs[0], mix.inputs[1])
    links.new(emission.outputs[0], mix.inputs[2])
    output = nodes.new("ShaderNodeOutputMaterial")
    output.location = (300, 100)
    links.new(mix.outputs[0], output.inputs["Surface"])
    return material


def gaussian_node_group() -> bpy.types.GeometryNodeTree:
    """The shared geometry-node group (built once per file, rebuilt when outdated)."""
    group = bpy.data.node_groups.get(GROUP_NAME)
    if group is not None and group.bl_idname == "GeometryNodeTree" and group.get("esgs_version") == TREE_VERSION:
        return group
    if group is None or group.bl_idname != "GeometryNodeTree":
        group = bpy.data.node_groups.new(GROUP_NAME, "GeometryNodeTree")
    group.nodes.clear()
    group.interface.clear()
    group["esgs_version"] = TREE_VERSION
    _build_tree(group, gaussian_material())
    return group


def _build_tree(group: bpy.types.GeometryNodeTree, material: bpy.types.Material) -> None:
    interface = group.interface
    interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    for name, socket_type, default, minimum, maximum, description in INPUTS:
        item = interface.new_socket(name, in_out="INPUT", socket_type=socket_type, description=description)
        item.default_value = default
        if minimum is not None:
            item.min_value = minimum
        if maximum is not None:
            item.max_value = maximum
    interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")

    nodes, links = group.nodes, group.links
    def add(kind: str, column: int, row: int, **settings):
        node = nodes.new(kind)
        for key, value in settings.items():
            setattr(node, key, value)
        node.location = (-1400 + 220 * column, -180 * row)
        return node

    def named(name: str, data_type: str, column: int, row: int):
        node = add("GeometryNodeInputNamedAttribute", column, row, data_type=data_type)
        node.inputs["Name"].default_value = name
        return node

    group_in = add("NodeGroupInput", 0, 0)
    group_out = add("NodeGroupOutput", 14, 0)

    # 1. hide faint Gaussians
    opacity = named("opacity", "FLOAT", 1, 1)
    faint = add("FunctionNodeCompare", 2, 1, data_type="FLOAT", operation="LESS_THAN")
    links.new(_socket(opacity.outputs, "Attribute"), _socket(faint.inputs, "A"))
    links.new(group_in.outputs["Opacity Min"], _socket(faint.inputs, "B"))
    drop_faint = add("GeometryNodeDeleteGeometry", 3, 0, domain="POINT")
    links.new(group_in.outputs["Geometry"], drop_faint.inputs["Geometry"])
    links.new(faint.outputs["Result"], drop_faint.inputs["Selection"])

    # 2. keep a random subset of about Max Display points: probability = max / count
    size = add("GeometryNodeAttributeDomainSize", 4, 2, component="POINTCLOUD")
    links.new(drop_faint.outputs["Geometry"], size.inputs["Geometry"])
    ratio = add("ShaderNodeMath", 5, 2, operation="DIVIDE")
    links.new(group_in.outputs["Max Display"], ratio.inputs[0])
    links.new(size.outputs["Point Count"], ratio.inputs[1])
    keep = add("FunctionNodeRandomValue", 6, 2, data_type="BOOLEAN")
    links.new(ratio.outputs[0], _socket(keep.inputs, "Probability"))
    links.new(group_in.outputs["Seed"], _socket(keep.inputs, "Seed"))
    drop = add("FunctionNodeBooleanMath", 7, 2, operation="NOT")
    links.new(_socket(keep.outputs, "Value"), drop.inputs[0])
    subset = add("GeometryNodeDeleteGeometry", 8, 0, domain="POINT")
    links.new(drop_faint.outputs["Geometry"], subset.inputs["Geometry"])
    links.new(drop.outputs[0], subset.inputs["Selection"])

    # 3. display colour: own colour or heat map of the distance
    colour = named("color", "FLOAT_COLOR", 7, 4)
    distance = named("distance", "FLOAT", 5, 5)
    to_unit = add("ShaderNodeMapRange", 6, 5, clamp=True)
    links.new(_socket(distance.outputs, "Attribute"), _socket(to_unit.inputs, "Value"))
    links.new(group_in.outputs["Distance Min"], _socket(to_unit.inputs, "From Min"))
    links.new(group_in.outputs["Distance Max"], _socket(to_unit.inputs, "From Max"))
    ramp = add("ShaderNodeValToRGB", 7, 6)
    elements = ramp.color_ramp.elements
    while len(elements) > 1:
        elements.remove(elements[-1])
    elements[0].position, elements[0].color = HEAT_COLOURS[0]
    for position, rgba in HEAT_COLOURS[1:]:
        elements.new(position).color = rgba
    links.new(_socket(to_unit.outputs, "Result"), ramp.inputs["Factor"])
    pick_colour = add("GeometryNodeSwitch", 8, 5, input_type="RGBA")
    links.new(group_in.outputs["Heat Map"], pick_colour.inputs["Switch"])
    links.new(_socket(colour.outputs, "Attribute"), pick_colour.inputs["False"])
    links.new(ramp.outputs["Color"], pick_colour.inputs["True"])
    store_colour = add("GeometryNodeStoreNamedAttribute", 9, 0, data_type="FLOAT_COLOR", domain="POINT")
    store_colour.inputs["Name"].default_value = DISPLAY_COLOR
    links.new(subset.outputs["Geometry"], store_colour.inputs["Geometry"])
    links.new(pick_colour.outputs["Output"], _socket(store_colour.inputs, "Value"))

    # the heat map is shown opaque; the Gaussians' own look uses their opacity
    pick_alpha = add("GeometryNodeSwitch", 9, 3, input_type="FLOAT")
    links.new(group_in.outputs["Heat Map"], pick_alpha.inputs["Switch"])
    links.new(_socket(opacity.outputs, "Attribute"), pick_alpha.inputs["False"])
    pick_alpha.inputs["True"].default_value = 1.0
    store_alpha = add("GeometryNodeStoreNamedAttribute", 10, 0, data_type="FLOAT", domain="POINT")
    store_alpha.inputs["Name"].default_value = DISPLAY_ALPHA
    links.new(store_colour.outputs["Geometry"], store_alpha.inputs["Geometry"])
    links.new(pick_alpha.outputs["Output"], _socket(store_alpha.inputs, "Value"))

    # 4a. points
    radius = add("GeometryNodeSetPointRadius", 11, 1)
    links.new(store_alpha.outputs["Geometry"], radius.inputs["Points"])
    links.new(group_in.outputs["Point Radius"], radius.inputs["Radius"])

    # 4b. ellipsoids: unit ico sphere scaled by the Gaussian's axes and rotated
    sphere = add("GeometryNodeMeshIcoSphere", 10, 3)
    sphere.inputs["Radius"].default_value = 1.0
    sphere.inputs["Subdivisions"].default_value = 2
    smooth = add("GeometryNodeSetShadeSmooth", 11, 3)
    links.new(sphere.outputs["Mesh"], smooth.inputs["Mesh"])
    rotation = named("rotation", "QUATERNION", 10, 4)
    scale = named("scale", "FLOAT_VECTOR", 9, 6)
    size_times = add("ShaderNodeVectorMath", 10, 6, operation="SCALE")
    links.new(_socket(scale.outputs, "Attribute"), size_times.inputs[0])
    links.new(group_in.outputs["Ellipsoid Size"], _socket(size_times.inputs, "Scale"))
    instances = add("GeometryNodeInstanceOnPoints", 12, 2)
    links.new(store_alpha.outputs["Geometry"], instances.inputs["Points"])
    links.new(smooth.outputs["Mesh"], instances.inputs["Instance"])
    links.new(_socket(rotation.outputs, "Attribute"), instances.inputs["Rotation"])
    links.new(size_times.outputs["Vector"], instances.inputs["Scale"])

    choose = add("GeometryNodeSwitch", 13, 0, input_type="GEOMETRY")
    links.new(group_in.outputs["Ellipsoids"], choose.inputs["Switch"])
    links.new(radius.outputs["Points"], choose.inputs["False"])
    links.new(instances.outputs["Instances"], choose.inputs["True"])
    set_material = add("GeometryNodeSetMaterial", 13, 2)
    set_material.inputs["Material"].default_value = material
    links.new(choose.outputs["Output"], set_material.inputs["Geometry"])
    links.new(set_material.outputs["Geometry"], group_out.inputs["Geometry"])


def input_identifiers(group: bpy.types.NodeTree) -> dict[str, str]:
    """Modifier key of each group input, by name (``{"Opacity Min": "Socket_2", ...}``)."""
    return {item.name: item.identifier for item in group.interface.items_tree
            if item.item_type == "SOCKET" and item.in_out == "INPUT"}


def add_gaussian_modifier(obj: bpy.types.Object, **inputs: Any) -> bpy.types.NodesModifier:
    """Add (or reuse) the display modifier on ``obj`` and set its inputs by name.

    Keyword names are the input names with spaces as underscores
    (``opacity_min=0.2, max_display=100_000, ellipsoids=True``).
    """
    modifier = obj.modifiers.get(MODIFIER_NAME)
    if modifier is None:
        modifier = obj.modifiers.new(MODIFIER_NAME, "NODES")
    modifier.node_group = gaussian_node_group()
    set_display_inputs(obj, **inputs)
    return modifier


def set_display_inputs(obj: bpy.types.Object, **inputs: Any) -> None:
    """Change the display modifier's inputs by name (see :func:`add_gaussian_modifier`)."""
    modifier = obj.modifiers[MODIFIER_NAME]
    identifiers = input_identifiers(modifier.node_group)
    for key, value in inputs.items():
        name = key.replace("_", " ").title() if key.replace("_", " ").title() in identifiers else key
        if name not in identifiers:
            raise KeyError(f"the Gaussian display has no input {key!r} (inputs: {', '.join(identifiers)})")
        modifier[identifiers[name]] = value
    obj.update_tag()


def display_input(obj: bpy.types.Object, name: str) -> Any:
    """Current value of one display input (by its name, e.g. ``"Distance Max"``)."""
    modifier = obj.modifiers[MODIFIER_NAME]
    return modifier[input_identifiers(modifier.node_group)[name]]
