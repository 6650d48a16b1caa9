"""Procedural Mars materials for Cycles: reddish regolith, sand, bedrock and dusty rocks.

Everything is built from Blender's procedural nodes (noise, colour ramps, a vertex
attribute), so nothing is downloaded and the result is the same on every machine.

The materials never perturb the shading normal (no bump or normal map): the Cycles Normal
pass must stay the geometric normal of the mesh, because the exported normal maps are
ground truth.
"""
from __future__ import annotations

from typing import Optional

import bpy

from ..core.terrain.palette import MARS_PALETTE, ScenePalette

#: Name of the per-vertex float attribute (0 = bedrock, 1 = loose sand) on the terrain mesh.
SAND_ATTRIBUTE = "esgs_sand"

# Linear-space albedos, chosen to look like Mars rover imagery under a white sun
_SAND_DARK = (0.32, 0.14, 0.06, 1.0)
_SAND_LIGHT = (0.52, 0.26, 0.12, 1.0)
_BEDROCK_DARK = (0.20, 0.11, 0.07, 1.0)
_BEDROCK_LIGHT = (0.40, 0.22, 0.12, 1.0)
_DUST = (0.60, 0.36, 0.20, 1.0)
_BASALTIC_SAND = (0.09, 0.065, 0.05, 1.0)
_ROCK_DARK = (0.06, 0.045, 0.04, 1.0)
_ROCK_LIGHT = (0.20, 0.13, 0.09, 1.0)


def _socket(sockets: bpy.types.NodeInputs | bpy.types.NodeOutputs, name: str, kind: str | None = None):
    """The enabled socket called ``name`` (optionally of type ``kind``, e.g. 'RGBA').

    Mix nodes carry one socket per data type under the same name; only the one matching
    the node's data type is enabled.
    """
    for socket in sockets:
        if socket.name == name and socket.enabled and (kind is None or socket.type == kind):
            return socket
    raise KeyError(f"no enabled socket {name!r} ({kind})")


def _color_ramp(nodes: bpy.types.Nodes, low: tuple, high: tuple, low_pos: float = 0.3, high_pos: float = 0.7):
    ramp = nodes.new("ShaderNodeValToRGB")
    elements = ramp.color_ramp.elements
    elements[0].position, elements[0].color = low_pos, low
    elements[1].position, elements[1].color = high_pos, high
    return ramp


def _noise(nodes: bpy.types.Nodes, links: bpy.types.NodeLinks, coordinates, scale: float, detail: float,
           roughness: float = 0.55):
    """A 3D noise texture of the vector output ``coordinates``; returns its Fac output."""
    noise = nodes.new("ShaderNodeTexNoise")
    noise.noise_dimensions = "3D"
    noise.inputs["Scale"].default_value = scale
    noise.inputs["Detail"].default_value = detail
    noise.inputs["Roughness"].default_value = roughness
    links.new(coordinates, noise.inputs["Vector"])
    return noise.outputs["Fac"]


def _map_range(nodes: bpy.types.Nodes, links: bpy.types.NodeLinks, value, from_min: float, from_max: float,
               to_min: float = 0.0, to_max: float = 1.0):
    """A (clamped, linear) Map Range node of the float output ``value``; returns its Result output."""
    node = nodes.new("ShaderNodeMapRange")
    node.inputs["From Min"].default_value = from_min
    node.inputs["From Max"].default_value = from_max
    node.inputs["To Min"].default_value = to_min
    node.inputs["To Max"].default_value = to_max
    links.new(value, node.inputs["Value"])
    return node.outputs["Result"]


def _multiply(nodes: bpy.types.Nodes, links: bpy.types.NodeLinks, value_a, value_b):
    """The product of two float outputs (a Math node); returns its Value output."""
    node = nodes.new("ShaderNodeMath")
    node.operation = "MULTIPLY"
    links.new(value_a, node.inputs[0])
    links.new(value_b, node.inputs[1])
    return node.outputs["Value"]


def _color(nodes: bpy.types.Nodes, rgba: tuple):
    """A constant colour (an RGB node); returns its Color output."""
    node = nodes.new("ShaderNodeRGB")
    node.outputs["Color"].default_value = rgba
    return node.outputs["Color"]


def _cover(nodes: bpy.types.Nodes, links: bpy.types.NodeLinks, albedo, rgba: tuple, value,
           from_min: float, from_max: float, most: float):
    """``albedo`` covered with the colour ``rgba`` (dust, dark sand): not at all where the float
    output ``value`` is at most ``from_min``, by ``most`` where it is at least ``from_max``."""
    amount = _map_range(nodes, links, value, from_min, from_max, 0.0, most)
    return _mix_color(nodes, links, amount, albedo, _color(nodes, rgba))


def _modulate(nodes: bpy.types.Nodes, links: bpy.types.NodeLinks, albedo, noise, low: float, high: float):
    """``albedo`` scaled by ``low`` to ``high`` as the noise output ``noise`` goes from 0.3 to 0.7
    (most of a noise's values): fine texture that keeps close-up views matchable."""
    gain = _map_range(nodes, links, noise, 0.3, 0.7, low, high)
    scaled = nodes.new("ShaderNodeVectorMath")
    scaled.operation = "SCALE"
    links.new(albedo, scaled.inputs[0])
    links.new(gain, scaled.inputs["Scale"])
    return scaled.outputs["Vector"]


def _mix_color(nodes: bpy.types.Nodes, links: bpy.types.NodeLinks, factor, color_a, color_b):
    """A Mix (colour) node blending two colour outputs by a float output; returns its result."""
    mix = nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    links.new(factor, _socket(mix.inputs, "Factor", "VALUE"))
    links.new(color_a, _socket(mix.inputs, "A", "RGBA"))
    links.new(color_b, _socket(mix.inputs, "B", "RGBA"))
    return _socket(mix.outputs, "Result", "RGBA")


def _new_material(name: str) -> tuple[bpy.types.Material, bpy.types.Nodes, bpy.types.NodeLinks, bpy.types.Node]:
    material = bpy.data.materials.new(name)
    if material.node_tree is None:  # Blender < 5 made node-less materials by default
        material.use_nodes = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    nodes.clear()
    output = nodes.new("ShaderNodeOutputMaterial")
    shader = nodes.new("ShaderNodeBsdfPrincipled")
    shader.inputs["Roughness"].default_value = 0.95
    # regolith is almost perfectly diffuse; a little specular keeps rocks from looking flat
    shader.inputs["Specular IOR Level"].default_value = 0.15
    links.new(shader.outputs["BSDF"], output.inputs["Surface"])
    return material, nodes, links, shader


def _saturated(nodes, links, color, saturation: float):
    """``color`` with its saturation scaled by ``saturation`` (1: the socket itself, no node, so
    the default look renders exactly as before)."""
    if saturation == 1.0:
        return color
    node = nodes.new("ShaderNodeHueSaturation")
    node.inputs["Saturation"].default_value = float(saturation)
    links.new(color, node.inputs["Color"])
    return node.outputs["Color"]


def make_terrain_material(name: str = "ESGS Mars terrain", *, saturation: float = 1.0) -> bpy.types.Material:
    """Regolith material: sand vs bedrock from the ``esgs_sand`` vertex attribute, noise variation, dust.

    Texture coordinates are object-space (metres for the terrain, which is not scaled), so
    the pattern keeps its size whatever the terrain resolution. ``saturation``: the albedo's
    (0 grey; a scene palette's ``surface_saturation``).
    """
    material, nodes, links, shader = _new_material(name)
    coordinates = nodes.new("ShaderNodeTexCoord").outputs["Object"]

    fine = _noise(nodes, links, coordinates, scale=2.5, detail=3.0, roughness=0.6)  # pebbles and clods, ~0.4 m
    coarse = _noise(nodes, links, coordinates, scale=0.08, detail=3.0)  # albedo patches, ~10 m
    # granules, ~5 cm: texture for matching
    grain = _noise(nodes, links, coordinates, scale=20.0, detail=1.0, roughness=0.5)

    sand_ramp = _color_ramp(nodes, _SAND_DARK, _SAND_LIGHT, 0.35, 0.65)
    bedrock_ramp = _color_ramp(nodes, _BEDROCK_DARK, _BEDROCK_LIGHT, 0.3, 0.7)
    links.new(fine, sand_ramp.inputs["Fac"])
    links.new(fine, bedrock_ramp.inputs["Fac"])

    sand = nodes.new("ShaderNodeAttribute")
    sand.attribute_type = "GEOMETRY"
    sand.attribute_name = SAND_ATTRIBUTE
    ground = _mix_color(nodes, links, sand.outputs["Fac"], bedrock_ramp.outputs["Color"], sand_ramp.outputs["Color"])
    ground = _add_basaltic_lag(nodes, links, coordinates, sand.outputs["Fac"], ground)

    # bright dust settles in patches; the coarse noise decides where
    albedo = _cover(nodes, links, ground, _DUST, coarse, 0.45, 0.75, most=0.45)
    # granules darken or lighten the albedo by up to ~50 %, so close-up views keep texture
    textured = _modulate(nodes, links, albedo, grain, 0.5, 1.45)
    pebbled = _add_pebbles(nodes, links, coordinates, textured, scale=9.0, fraction=0.4, radius=0.2)
    pebbled = _add_pebbles(nodes, links, coordinates, pebbled, scale=2.5, fraction=0.12, radius=0.16)
    links.new(_saturated(nodes, links, pebbled, saturation), shader.inputs["Base Color"])
    return material


def _add_basaltic_lag(nodes: bpy.types.Nodes, links: bpy.types.NodeLinks, coordinates, sand_amount, albedo):
    """Darken ``albedo`` with patches of dark basaltic sand, on sand only (``sand_amount`` 0..1).

    Martian sand is basaltic and dark where it is fresh; wind sorts it into darker lags of
    coarse grains and brighter dust-coated patches, at every scale from ripples to dunes.
    A fractal noise thresholded near its median gives patches with crisp, irregular edges
    from ~0.2 m to a few metres: the blobs and corners a feature matcher needs on sand,
    which otherwise only shades smoothly.
    """
    patches = _noise(nodes, links, coordinates, scale=0.45, detail=6.0, roughness=0.62)  # ~2 m, finer lobes
    edge = _map_range(nodes, links, patches, 0.53, 0.57, 0.0, 0.6)
    amount = _multiply(nodes, links, edge, sand_amount)
    return _mix_color(nodes, links, amount, albedo, _color(nodes, _BASALTIC_SAND))


def _add_pebbles(nodes: bpy.types.Nodes, links: bpy.types.NodeLinks, coordinates, albedo, scale: float,
                 fraction: float, radius: float):
    """Scatter pebbles (dark or light, one per Voronoi cell in ``fraction`` of the cells) over ``albedo``.

    ``scale`` cells per metre; a pebble's radius is ``radius`` cells, with a soft edge. Distinct
    blobs give feature matchers (SIFT) something to hold on to, as real regolith does.
    """
    cells = nodes.new("ShaderNodeTexVoronoi")
    # 2D cells on the ground plane: a third of the cost of 3D cells, and pebbles lie on the ground
    cells.voronoi_dimensions = "2D"
    cells.feature = "F1"
    cells.inputs["Scale"].default_value = scale
    links.new(coordinates, cells.inputs["Vector"])
    edge = _map_range(nodes, links, cells.outputs["Distance"], radius * 1.3, radius * 0.9)
    cell_random = nodes.new("ShaderNodeSeparateColor")
    links.new(cells.outputs["Color"], cell_random.inputs["Color"])
    present = nodes.new("ShaderNodeMath")
    present.operation = "GREATER_THAN"
    present.inputs[1].default_value = 1.0 - fraction
    links.new(cell_random.outputs["Red"], present.inputs[0])
    amount = _multiply(nodes, links, edge, present.outputs["Value"])
    shade = _color_ramp(nodes, _ROCK_DARK, _DUST, 0.0, 1.0)
    links.new(cell_random.outputs["Green"], shade.inputs["Fac"])
    return _mix_color(nodes, links, amount, albedo, shade.outputs["Color"])


def make_rock_material(name: str = "ESGS Mars rock", *, saturation: float = 1.0) -> bpy.types.Material:
    """Dark basaltic rock with mottled albedo and dust on its upward-facing parts (``saturation``
    as :func:`make_terrain_material`)."""
    material, nodes, links, shader = _new_material(name)
    shader.inputs["Roughness"].default_value = 0.8
    coordinates = nodes.new("ShaderNodeTexCoord").outputs["Object"]
    mottling = _noise(nodes, links, coordinates, scale=6.0, detail=3.0, roughness=0.65)
    rock_ramp = _color_ramp(nodes, _ROCK_DARK, _ROCK_LIGHT, 0.3, 0.75)
    links.new(mottling, rock_ramp.inputs["Fac"])

    # dust on faces that look up: the geometric normal's z, read but never used for shading
    geometry = nodes.new("ShaderNodeNewGeometry")
    up = nodes.new("ShaderNodeSeparateXYZ")
    links.new(geometry.outputs["Normal"], up.inputs["Vector"])
    albedo = _cover(nodes, links, rock_ramp.outputs["Color"], _DUST, up.outputs["Z"], 0.75, 1.0, most=0.35)
    # fine speckle (vesicles, crystals) keeps close-up rock faces textured; coordinates are
    # the unit prototype's, so ~40 per rock diameter
    speckle = _noise(nodes, links, coordinates, scale=40.0, detail=1.0)
    links.new(_saturated(nodes, links, _modulate(nodes, links, albedo, speckle, 0.6, 1.4), saturation),
              shader.inputs["Base Color"])
    return material


def make_sky_world(name: str, *, sky: bool, sun_elevation_deg: float = 30.0,
                   palette: Optional[ScenePalette] = None) -> bpy.types.World:
    """World shader: a Mars sky gradient with a dusty horizon; black to the camera when ``sky`` is False.

    With ``sky`` False the world still lights the scene (the dusty Martian sky is a strong
    ambient source: without it every shadow would be pitch black), but camera rays see
    black, so a view past the terrain's edge shows no sky. The gradient depends on the view direction's elevation only: butterscotch near the
    horizon, darker brown towards the zenith, and a ground-coloured band below the horizon
    so views that look past the terrain's edge see a plausible distant plain. These pixels
    have no surface, so they are masked out of the priors (mask 0). The sky's strength
    follows the sun's elevation so a low sun gives a dimmer sky. ``palette``: the gradient's
    colours (:mod:`esgs.core.terrain.palette`; default the fixed Mars sky).
    """
    import math

    world = bpy.data.worlds.new(name)
    if world.node_tree is None:
        world.use_nodes = True
    nodes, links = world.node_tree.nodes, world.node_tree.links
    nodes.clear()
    output = nodes.new("ShaderNodeOutputWorld")
    background = nodes.new("ShaderNodeBackground")
    links.new(background.outputs["Background"], output.inputs["Surface"])
    # item assignment skips Cycles' update callback, which fails while no scene uses this world
    world.cycles_visibility["camera"] = bool(sky)
    coords = nodes.new("ShaderNodeTexCoord")
    direction = nodes.new("ShaderNodeSeparateXYZ")
    links.new(coords.outputs["Generated"], direction.inputs["Vector"])
    # elevation z in [-1, 1] -> ramp position in [0, 1]; horizon at 0.5
    to_ramp = _map_range(nodes, links, direction.outputs["Z"], -1.0, 1.0)
    ramp = nodes.new("ShaderNodeValToRGB")
    palette = palette or MARS_PALETTE
    palette.validate()
    elements = ramp.color_ramp.elements
    elements[0].position, elements[0].color = 0.0, (*palette.nadir, 1.0)  # distant ground
    elements[1].position, elements[1].color = 1.0, (*palette.zenith, 1.0)
    for position, color in ((0.495, palette.distant_ground),  # ground just below the horizon
                            (0.505, palette.horizon),  # bright dusty horizon
                            (palette.haze_height, palette.haze)):
        element = elements.new(position)
        element.color = (*color, 1.0)
    links.new(to_ramp, ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], background.inputs["Color"])
    background.inputs["Strength"].default_value = palette.strength * (
        0.15 + 0.35 * max(0.0, math.sin(math.radians(sun_elevation_deg))))
    return world
