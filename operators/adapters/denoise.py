"""Open Image Denoise as Blender ships it: the compositor's Denoise node, run headless.

:func:`denoise_canvas` puts a colour canvas and its albedo and normal guides into scratch float
images, wires them into the Denoise node (HDR on, prefilter None: the guides are exact, not
rendered) of a scratch compositing node group on a scratch scene whose resolution is the canvas's,
and renders that scene: with no Render Layers node in the compositor Blender renders no 3D scene,
it only composites. The result is written to a temporary OpenEXR (32-bit float) and read back.
Every scratch datablock and file is removed, whatever happens; the user's scenes are not touched.

:func:`denoise_bake` denoises every object of a ``BakeResult`` per UV island
(``lmdp_addon.bake.islands``: each island laid out alone with its own continuation around it, so
no light crosses from one island to another), re-fills the margin, and keeps the raw lightmap in
``ObjectBake.raw_image``.
"""
import os
import shutil
import tempfile

import bpy
import numpy as np

from ...lmdp_addon.bake.islands import denoised_image
from ...lmdp_addon.errors import SceneError

SCRATCH = "LMDP denoise"


def _scratch_image(name, canvas):
    H, W = canvas.shape[:2]
    image = bpy.data.images.new(name, W, H, alpha=True, float_buffer=True)
    image.colorspace_settings.name = 'Non-Color'
    rgba = np.ones((H, W, 4), np.float32)
    rgba[..., :3] = canvas[..., :3]
    image.pixels.foreach_set(rgba.reshape(-1))
    image.update()
    return image


def denoise_canvas(color, albedo=None, normal=None, threads=None):
    """The (H, W, 3) float32 canvas ``color`` denoised by OIDN (the compositor's Denoise node),
    guided by ``albedo`` and ``normal`` (H, W, 3) when given; ``threads``: the compositor's
    thread count (None: Blender's automatic choice). Raises ``SceneError`` if Blender cannot run
    it."""
    color = np.asarray(color, dtype=np.float32)
    H, W = color.shape[:2]
    made_images, scene, tree, folder = [], None, None, tempfile.mkdtemp(prefix="lmdp_denoise_")
    try:
        scene = bpy.data.scenes.new(SCRATCH)
        tree = bpy.data.node_groups.new(SCRATCH, "CompositorNodeTree")
        scene.compositing_node_group = tree
        tree.interface.new_socket("Image", in_out='OUTPUT', socket_type='NodeSocketColor')
        node = tree.nodes.new("CompositorNodeDenoise")
        node.inputs["HDR"].default_value = True
        node.inputs["Prefilter"].default_value = 'None'
        node.inputs["Quality"].default_value = 'High'
        for socket, canvas in (("Image", color), ("Albedo", albedo), ("Normal", normal)):
            if canvas is None:
                continue
            made_images.append(_scratch_image(f"{SCRATCH} {socket}", np.asarray(canvas, np.float32)))
            source = tree.nodes.new("CompositorNodeImage")
            source.image = made_images[-1]
            tree.links.new(source.outputs["Image"], node.inputs[socket])
        output = tree.nodes.new("NodeGroupOutput")
        tree.links.new(node.outputs["Image"], output.inputs[0])
        render = scene.render
        render.resolution_x, render.resolution_y, render.resolution_percentage = W, H, 100
        render.image_settings.file_format = 'OPEN_EXR'
        render.image_settings.color_depth = '32'
        render.image_settings.color_mode = 'RGB'
        render.use_compositing = True
        if threads:
            render.threads_mode, render.threads = 'FIXED', int(threads)
        path = os.path.join(folder, "denoised.exr")
        render.filepath = path
        with bpy.context.temp_override(scene=scene):
            done = bpy.ops.render.render(write_still=True, scene=scene.name)
        if done != {'FINISHED'} or not os.path.exists(path):
            raise SceneError("Blender's compositor did not denoise the lightmap (the Denoise node needs "
                             "a Blender built with Open Image Denoise): turn LMDP > Bake > Denoise off")
        result = bpy.data.images.load(path)
        made_images.append(result)
        if tuple(result.size) != (W, H):
            raise SceneError(f"The compositor returned a {tuple(result.size)} image for a {W} x {H} "
                             "lightmap canvas: turn LMDP > Bake > Denoise off")
        pixels = np.empty(W * H * result.channels, np.float32)
        result.pixels.foreach_get(pixels)
        return pixels.reshape(H, W, result.channels)[..., :3].copy()
    finally:
        for image in made_images:
            bpy.data.images.remove(image)
        if scene is not None:
            bpy.data.scenes.remove(scene)
        if tree is not None:
            bpy.data.node_groups.remove(tree)
        shutil.rmtree(folder, ignore_errors=True)


def denoise_bake(result, inputs, margin):
    """Denoise every object of ``result`` (``BakeResult``) that has a
    ``lmdp_addon.bake.islands.DenoiseInput`` in ``inputs`` {name: input}: its ``image`` becomes the
    denoised one, ``raw_image`` keeps the path-traced one and ``denoised_value`` holds the
    denoised texels (``value`` and ``standard_error`` stay the path tracer's)."""
    for ob in result.objects:
        prepared = inputs.get(ob.name)
        if prepared is None:
            continue
        canvas = denoise_canvas(prepared.color, prepared.albedo, prepared.normal)
        values, image = denoised_image(ob, prepared, canvas, margin)
        ob.raw_image, ob.image, ob.denoised_value = ob.image, image, values
    return result
