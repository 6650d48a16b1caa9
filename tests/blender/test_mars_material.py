"""The procedural Mars materials (esgs_addon/mars_material.py): the albedo is textured, the
shading normal is never touched (the Normal pass is exported as ground truth)."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.esgs_addon.mars_material import SAND_ATTRIBUTE, make_rock_material, make_terrain_material


def _upstream(socket) -> set[str]:
    """The kinds of every node feeding ``socket``, however far back."""
    seen, pending = {}, [link.from_node for link in socket.links]
    while pending:
        node = pending.pop()
        if node.name not in seen:
            seen[node.name] = node.bl_idname
            pending.extend(link.from_node for source in node.inputs for link in source.links)
    return set(seen.values())


@pytest.mark.parametrize("make", [make_terrain_material, make_rock_material])
def test_albedo_is_textured_and_the_normal_untouched(make):
    tree = make().node_tree
    shader = next(node for node in tree.nodes if node.bl_idname == "ShaderNodeBsdfPrincipled")
    albedo = _upstream(shader.inputs["Base Color"])
    assert {"ShaderNodeTexNoise", "ShaderNodeMapRange", "ShaderNodeMix", "ShaderNodeVectorMath"} <= albedo
    assert not shader.inputs["Normal"].is_linked
    assert not {"ShaderNodeBump", "ShaderNodeNormalMap", "ShaderNodeDisplacement"} & {n.bl_idname for n in tree.nodes}
    output = next(node for node in tree.nodes if node.bl_idname == "ShaderNodeOutputMaterial")
    assert not output.inputs["Displacement"].is_linked


def test_terrain_reads_the_sand_attribute_and_scatters_pebbles():
    tree = make_terrain_material().node_tree
    attributes = [node.attribute_name for node in tree.nodes if node.bl_idname == "ShaderNodeAttribute"]
    assert attributes == [SAND_ATTRIBUTE]
    cells = [node for node in tree.nodes if node.bl_idname == "ShaderNodeTexVoronoi"]
    assert sorted(node.inputs["Scale"].default_value for node in cells) == [2.5, 9.0]
    gains = sorted((node.inputs["To Min"].default_value, node.inputs["To Max"].default_value)
                   for node in tree.nodes if node.bl_idname == "ShaderNodeMapRange"
                   and any(link.to_node.bl_idname == "ShaderNodeVectorMath" for link in node.outputs["Result"].links))
    assert gains == [pytest.approx((0.5, 1.45))]  # the granule texture scales the albedo by 0.5 to 1.45


def _ramp_stops(world) -> list[tuple[float, tuple[float, ...]]]:
    ramp = next(node for node in world.node_tree.nodes if node.bl_idname == "ShaderNodeValToRGB")
    return [(round(e.position, 3), tuple(round(c, 4) for c in e.color[:3])) for e in ramp.color_ramp.elements]


def test_the_default_sky_keeps_the_generators_mars_gradient():
    from esgs.esgs_addon.mars_material import make_sky_world

    # the colours every earlier scene was rendered with: a default that moved would change them all
    assert _ramp_stops(make_sky_world("sky", sky=True)) == [
        (0.0, (0.16, 0.08, 0.04)), (0.495, (0.3, 0.16, 0.08)), (0.505, (0.72, 0.5, 0.32)),
        (0.62, (0.45, 0.28, 0.16)), (1.0, (0.2, 0.12, 0.07))]


def _render_sky(world, tmp_path) -> np.ndarray:
    """A small Cycles render of ``world`` alone, looking at the horizon (Standard view: the
    world's colours as they are)."""
    import bpy

    scene = bpy.data.scenes.new("sky probe")
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 1
    scene.cycles.device = "CPU"
    scene.render.resolution_x, scene.render.resolution_y = 8, 8
    scene.view_settings.view_transform = "Standard"
    scene.world = world
    camera_data = bpy.data.cameras.new("sky probe")
    camera = bpy.data.objects.new("sky probe", camera_data)
    scene.collection.objects.link(camera)
    camera.rotation_euler = (1.5708 + 0.3, 0.0, 0.0)  # level, then tilted up: horizon haze to higher sky
    scene.camera = camera
    scene.render.dither_intensity = 0.0
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(tmp_path / "sky.png")
    try:
        bpy.ops.render.render(write_still=True, scene=scene.name)
        image = bpy.data.images.load(str(tmp_path / "sky.png"))
        pixels = np.array(image.pixels[:], dtype=np.float32).reshape(8, 8, 4)[..., :3]
        bpy.data.images.remove(image)
    finally:
        bpy.data.objects.remove(camera)
        bpy.data.cameras.remove(camera_data)
        bpy.data.scenes.remove(scene)
    return pixels


def test_a_grey_palette_renders_a_grey_sky_and_the_mars_one_a_dusty_one(tmp_path):
    from esgs.core.terrain.palette import MARS_PALETTE, varied_palette
    from esgs.esgs_addon.mars_material import make_sky_world

    grey_seed = next(seed for seed in range(100) if len(set(varied_palette(seed).horizon)) == 1)
    grey = _render_sky(make_sky_world("grey", sky=True, sun_elevation_deg=60, palette=varied_palette(grey_seed)),
                       tmp_path)
    dusty = _render_sky(make_sky_world("dusty", sky=True, sun_elevation_deg=60, palette=MARS_PALETTE), tmp_path)
    assert float(grey.mean()) > 0.02 and float(dusty.mean()) > 0.02  # the camera sees the sky
    grey_rgb, dusty_rgb = grey.reshape(-1, 3).mean(0), dusty.reshape(-1, 3).mean(0)  # (one sample: noisy pixels)
    assert abs(float(grey_rgb[0] - grey_rgb[2])) < 0.01  # red equals blue: no tint
    assert float(dusty_rgb[0] - dusty_rgb[2]) > 0.1  # butterscotch: red well above blue


@pytest.mark.parametrize("make", [make_terrain_material, make_rock_material])
def test_a_palettes_surface_saturation_scales_the_albedo_and_one_adds_no_node(make):
    def saturation_nodes(material):
        return [node for node in material.node_tree.nodes if node.bl_idname == "ShaderNodeHueSaturation"]

    assert not saturation_nodes(make())  # the default material is the one every scene was rendered with
    grey = make(saturation=0.0)
    (node,) = saturation_nodes(grey)
    assert node.inputs["Saturation"].default_value == 0.0
    shader = next(n for n in grey.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    assert shader.inputs["Base Color"].links[0].from_node == node  # the last step before the shader
