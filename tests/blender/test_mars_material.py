"""The procedural Mars materials (esgs_addon/mars_material.py): the albedo is textured, the
shading normal is never touched (the Normal pass is exported as ground truth)."""
from __future__ import annotations

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
