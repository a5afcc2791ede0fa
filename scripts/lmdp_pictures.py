"""The pictures of ``scripts/lmdp_headless.py``: Cycles renders (Standard view transform) of the
solution with the scene camera, into the output folder.

``<name>_z.png`` (z as colours: ``lmdp.show_desirability`` + ``lmdp.view_desirability(target=
'RENDER')``), ``<name>_policy.png`` (``lmdp.show_policy(as_mesh=True)`` in the lit scene),
``<name>_probe.png`` (``lmdp.probe_policy``), ``<name>_lightmaps.png`` (the baked lightmaps on
their objects) and, when matplotlib is importable, ``<name>_z_legend.png`` (the z picture with
its colour bar). The operators run through ``run_operator`` of the headless script, so every
step lands in its summary.
"""
import importlib
import os
import time

#: Render size and samples of the pictures (small: they take seconds, not minutes, on a CPU).
PICTURE_SIZE = 320
PICTURE_SAMPLES = {"z": 16, "lit": 32}
#: Where the demo probes u* (a point on the floor in front of the boxes), per demo kind.
DEMO_PROBES = {"cornell": (0.12, -0.38, 0.0), "heavy": (0.12, -0.38, 0.0)}


def configure_render(scene, samples):
    """Cycles on the CPU at PICTURE_SIZE, Standard view transform, 8-bit PNG; OIDN when the
    samples are few for a lit scene (the colour renders are emission only and need none)."""
    scene.render.engine = 'CYCLES'
    scene.cycles.device = 'CPU'
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = samples > PICTURE_SAMPLES["z"]
    if scene.cycles.use_denoising:
        try:
            scene.cycles.denoiser = 'OPENIMAGEDENOISE'
        except TypeError:  # a build without OIDN: more samples instead
            scene.cycles.use_denoising = False
            scene.cycles.samples = 2 * samples
    scene.view_settings.view_transform = 'Standard'
    scene.view_settings.look = 'None'
    scene.render.resolution_x = scene.render.resolution_y = PICTURE_SIZE
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.render.image_settings.file_format = 'PNG'
    scene.render.image_settings.color_mode = 'RGB'
    scene.render.image_settings.color_depth = '8'


def render_picture(scene, path, samples, steps):
    import bpy
    configure_render(scene, samples)
    scene.render.filepath = path
    start = time.perf_counter()
    print(f"[LMDP] rendering {os.path.basename(path)} ({PICTURE_SIZE}x{PICTURE_SIZE}, {samples} samples)", flush=True)
    bpy.ops.render.render(write_still=True)
    steps.append({"operator": "render.render", "arguments": {"filepath": path}, "status": "FINISHED",
                  "seconds": time.perf_counter() - start})
    return path


def _hide_generated(kind, hidden):
    import bpy
    for obj in bpy.data.objects:
        if obj.get("lmdp_generated") == kind:
            obj.hide_render = hidden


def submodule(extension, name):
    return importlib.import_module(f"{extension}.{name}")


def render_pictures(run_operator, extension, output, name, steps, explicit, demo):
    """The pictures of the module docstring; returns {kind: path}. ``run_operator(idname,
    steps, **kwargs)`` runs an operator and records the step; ``explicit``: the settings the user
    set (left alone); ``demo``: the demo's kind (it knows where to probe)."""
    import bpy
    scene = bpy.context.scene
    if scene.camera is None:
        print("[LMDP] no pictures: the scene has no camera", flush=True)
        return {}
    props = scene.lmdp
    if "display_subdivide" not in explicit:
        props.display_subdivide = True  # a faithful picture even on single-quad walls
    pictures = {}
    run_operator("lmdp.show_desirability", steps)
    run_operator("lmdp.view_desirability", steps, target='RENDER')
    try:
        pictures["z"] = render_picture(scene, os.path.join(output, f"{name}_z.png"), PICTURE_SAMPLES["z"], steps)
    finally:
        run_operator("lmdp.view_desirability", steps, target='RENDER', enable=False)
    legend = legend_picture(extension, scene, pictures["z"], os.path.join(output, f"{name}_z_legend.png"))
    if legend:
        pictures["z_legend"] = legend

    if "policy_subset" not in explicit:
        props.policy_subset = 'MOST_INFORMATIVE'
    if "policy_max_points" not in explicit:
        props.policy_max_points = 40
    if "policy_arrow_scale" not in explicit:
        props.policy_arrow_scale = 0.3 * scene_size(extension, scene)
    run_operator("lmdp.show_policy", steps, as_mesh=True)
    _hide_generated("probe", True)
    pictures["policy"] = render_picture(scene, os.path.join(output, f"{name}_policy.png"), PICTURE_SAMPLES["lit"], steps)

    location = DEMO_PROBES.get(demo)
    if location is None:  # a .blend file: probe where the policy is most informative
        view = submodule(extension, "operators.session").peek(scene).get("policy")
        states = submodule(extension, "operators.session").peek(scene).get("states")
        location = tuple(states.points[view.points[0]]) if view is not None and len(view.points) else None
    if location is not None:
        run_operator("lmdp.probe_policy", steps, use_cursor=False, location=location, as_mesh=True,
                     next_states=16)
        _hide_generated("policy", True)
        _hide_generated("probe", False)
        pictures["probe"] = render_picture(scene, os.path.join(output, f"{name}_probe.png"), PICTURE_SAMPLES["lit"], steps)
        _hide_generated("policy", False)

    lightmaps = lightmap_picture(extension, scene, os.path.join(output, f"{name}_lightmaps.png"), steps)
    if lightmaps:
        pictures["lightmaps"] = lightmaps
    return pictures


def lightmap_picture(extension, scene, path, steps):
    """The baked lightmaps shown on their objects (each object's preview material: emission =
    its ``<object>_lmdp_indirect`` image, i.e. E_ind/π as baked, no albedo), rendered like the z
    picture; the materials are restored afterwards. None when nothing was baked."""
    lightmaps = submodule(extension, "operators.adapters.lightmaps")
    materials = submodule(extension, "operators.adapters.materials")
    baked = [(obj, lightmaps.own_image(obj.name_full)) for obj in scene.objects
             if obj.type == 'MESH' and materials.is_local(obj)]
    baked = [(obj, image) for obj, image in baked if image is not None]
    if not baked:
        return None
    for obj, image in baked:
        materials.hook_preview(obj, image)
    _hide_generated("policy", True)
    _hide_generated("probe", True)
    try:
        return render_picture(scene, path, PICTURE_SAMPLES["z"], steps)
    finally:
        for obj, _image in baked:
            materials.unhook_preview(obj)
        _hide_generated("policy", False)
        _hide_generated("probe", False)


def scene_size(extension, scene):
    """Bounding-box diagonal of the captured scene over sqrt(3) (1 m for the Cornell box)."""
    arrays = submodule(extension, "operators.session").peek(scene).get("scene")
    return arrays.bounding_diagonal() / 3 ** 0.5 if arrays is not None else 1.0


def legend_picture(extension, scene, z_path, path):
    """The z picture beside its colour bar (matplotlib, when importable; else nothing)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    record = submodule(extension, "operators.session").peek(scene).get("display")
    colormap = submodule(extension, "lmdp_addon.display.colormap")
    import numpy as np
    scale = record.scale
    image = plt.imread(z_path)
    figure, axes = plt.subplots(figsize=(4.6, 3.6), dpi=100, gridspec_kw={"width_ratios": [1.0, 0.05]},
                                ncols=2, constrained_layout=True)
    axes[0].imshow(image)
    axes[0].set_axis_off()
    bar = colormap.colormap_srgb(np.linspace(0, 1, 256), record.colormap)
    ticks = np.linspace(0, 1, 5)
    axes[1].imshow(bar[::-1, None, :], aspect="auto", extent=(0, 1, 0, 1))
    axes[1].yaxis.tick_right()
    axes[1].set_yticks(ticks, scale.tick_labels(5))
    axes[1].set_xticks([])
    label = scale.label.replace("z: ", "z, ")
    axes[1].set_ylabel(label + (" (log)" if scale.log else ""), fontsize=8)
    axes[1].yaxis.set_label_position("right")
    axes[1].tick_params(labelsize=8)
    figure.savefig(path)
    plt.close(figure)
    return path
