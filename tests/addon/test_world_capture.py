"""The world capture (operators/adapters/world_capture.py) on bad or unusual worlds: what the user
is told, and that nothing of theirs changes."""
import bpy
import numpy as np
import pytest


@pytest.fixture
def capture(lmdp_ext):
    return lmdp_ext.sub("operators.adapters.world_capture")


def env_world(pixels=None, image=None):
    world = bpy.data.worlds.new("Sky")
    bpy.context.scene.world = world
    nodes, links = world.node_tree.nodes, world.node_tree.links
    tex = nodes.new("ShaderNodeTexEnvironment")
    tex.name = "HDRI"
    if image is None:
        h, w = pixels.shape[:2]
        image = bpy.data.images.new("Map", w, h, alpha=True, float_buffer=True)
        image.pixels.foreach_set(np.asarray(pixels, np.float32).ravel())
    tex.image = image
    links.new(tex.outputs["Color"], nodes["Background"].inputs["Color"])
    return world, tex


def test_world_invisible_to_diffuse_rays_is_black(fresh_scene, capture):
    world, _ = env_world(np.ones((4, 8, 4), np.float32))
    world.cycles_visibility.diffuse = False
    warnings = []
    radiance, env = capture.WorldReader(warnings).capture(world)
    assert env is None and np.all(radiance == 0)
    assert any("World 'Sky'" in w and "Diffuse" in w for w in warnings), warnings
    assert world.cycles_visibility.diffuse is False          # the user's setting is untouched


def test_missing_image_and_non_finite_pixels_are_named(fresh_scene, capture, tmp_path):
    image = bpy.data.images.new("Gone", 4, 4)
    image.source = 'FILE'
    image.filepath = str(tmp_path / "gone.exr")         # a file that is not there
    image.reload()
    world, _ = env_world(image=image)
    warnings = []
    radiance, env = capture.WorldReader(warnings).capture(world)
    assert env is None and np.all(radiance == 0)
    assert any("'Gone'" in w and "no pixels" in w and "World 'Sky'" in w for w in warnings), warnings
    px = np.ones((4, 8, 4), np.float32)
    px[1, 2, 0] = np.inf
    px[2, 3, 1] = np.nan
    world, _ = env_world(px)
    warnings = []
    radiance, env = capture.WorldReader(warnings).capture(world)
    assert env is not None and np.all(np.isfinite(env.radiance)) and env.radiance[1, 2, 0] == 0
    assert any("2 pixels" in w and "not finite" in w for w in warnings), warnings


@pytest.mark.parametrize("vector_type", ['POINT', 'TEXTURE', 'VECTOR', 'NORMAL'])
def test_mapping_rotation_is_read_exactly(fresh_scene, capture, vector_type):
    """A Mapping node that only turns directions (any vector type, uniform scale) becomes the map's
    rotation: the world direction d sees the pixel of the mapped direction, as Cycles'
    ``svm_mapping`` computes it (TEXTURE is the inverse transform)."""
    px = np.random.default_rng(0).random((8, 16, 4)).astype(np.float32)
    world, tex = env_world(px)
    nodes, links = world.node_tree.nodes, world.node_tree.links
    mapping = nodes.new("ShaderNodeMapping")
    mapping.vector_type = vector_type
    angles = (0.3, -0.2, 1.1)
    mapping.inputs["Rotation"].default_value = angles
    mapping.inputs["Scale"].default_value = (2.0, 2.0, 2.0)
    links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    warnings = []
    _, env = capture.WorldReader(warnings).capture(world)
    assert not warnings, warnings
    R = capture.euler_xyz(angles)
    expected = R.T if vector_type == 'TEXTURE' else R
    np.testing.assert_allclose(env.rotation, expected, atol=1e-12)
    # Blender's own Euler matrix agrees with the one the capture builds
    from mathutils import Euler
    np.testing.assert_allclose(np.array(Euler(angles, 'XYZ').to_matrix()), R, atol=1e-6)


def test_mapping_that_warps_directions_is_evaluated_per_direction(fresh_scene, capture):
    px = np.zeros((8, 16, 4), np.float32)
    px[..., :3] = np.linspace(0, 1, 16)[None, :, None]
    world, tex = env_world(px)
    nodes, links = world.node_tree.nodes, world.node_tree.links
    mapping = nodes.new("ShaderNodeMapping")
    mapping.name = "Squash"
    mapping.inputs["Scale"].default_value = (1.0, 3.0, 1.0)
    links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    warnings = []
    _, env = capture.WorldReader(warnings).capture(world)
    assert env is not None and np.allclose(env.rotation, np.eye(3))
    assert any("'Squash'" in w and "every direction" in w for w in warnings), warnings


def test_light_path_world_is_named(fresh_scene, capture):
    """A world that switches on the ray type can only be rendered as the camera sees it: the
    warning names the Light Path node and says what to do; the map is what the camera sees (the
    Background's white, Is Camera Ray = 1)."""
    world, tex = env_world(np.ones((4, 8, 4), np.float32))
    nodes, links = world.node_tree.nodes, world.node_tree.links
    path = nodes.new("ShaderNodeLightPath")
    path.name = "Camera?"
    mix = nodes.new("ShaderNodeMixShader")
    links.new(path.outputs["Is Camera Ray"], mix.inputs["Fac"])
    links.new(nodes["Background"].outputs[0], mix.inputs[2])         # what the camera sees
    links.new(mix.outputs[0], nodes["World Output"].inputs["Surface"])
    warnings = []
    radiance, env = capture.WorldReader(warnings).capture(world)
    assert env is not None
    np.testing.assert_allclose(radiance, 1.0, rtol=1e-3)
    assert any("'Camera?'" in w and "Light Path" in w and "diffuse rays" in w for w in warnings), warnings
    assert any("renders the world" in w and "'Mix Shader'" in w for w in warnings), warnings
