"""PHYSICAL-mode z is the discrete light transport solution: refining the state space brings it
closer to Cycles' bake of the same scene (issue 3, Accuracy)."""
import numpy as np
from scipy.spatial import cKDTree


def floor_texels(ext, scene_arrays, resolution):
    texels = ext.sub("lmdp_addon.texels")
    floor = scene_arrays.object_names.index("Floor")
    tris = np.flatnonzero(scene_arrays.triangle_object == floor)
    normals, _ = scene_arrays.triangle_geometry()
    return texels.rasterize_texels(scene_arrays.triangle_uv[tris], scene_arrays.corners()[tris],
                                   normals[tris], resolution)


def test_refinement_converges_towards_cycles(lmdp_ext, fresh_scene):
    """The floor's outgoing radiance z (albedo x irradiance / π, PHYSICAL mode) at every floor
    state against Cycles' DIFFUSE bake with DIRECT + INDIRECT + COLOR at the texel containing the
    state. The LMDP's discretisation error (piecewise-constant radiance of the states a ray
    lands in, noisy transitions) must shrink as points and rays are added: the mean bias and
    the per-point error both fall. Cycles' own noise is measured from two seeds."""
    import bpy
    demo = lmdp_ext.sub("operators.demo_scenes")
    session = lmdp_ext.sub("operators.session")
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    selection = list(bpy.context.selected_objects)
    floor_obj = bpy.data.objects["Floor"]
    R = 48
    # Both sides solve the full transport: Cycles' bounce limit raised far above what matters.
    refs = [demo.bake_cycles(bpy.context, floor_obj, 'DIFFUSE', ('DIRECT', 'INDIRECT', 'COLOR'), R,
                             samples=256, max_bounces=64, seed=s, clamp_indirect=0.0)[..., :3] for s in (1, 2)]
    cycles = 0.5 * (refs[0] + refs[1])
    for obj in selection:
        obj.select_set(True)
    s = fresh_scene.lmdp
    s.cost_mode, s.solver, s.rays_per_stratum = 'PHYSICAL', 'ITERATIVE', 4
    bias, rmse = [], []
    for points in (1000, 16000):
        s.point_count = points
        assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
        sess = session.session_for(fresh_scene)
        arrays, states, sol = sess.require("scene_arrays"), sess.require("states"), sess.require("solution")
        tex = floor_texels(lmdp_ext, arrays, R)
        ids = np.flatnonzero(states.point_object == arrays.object_names.index("Floor"))
        _, nearest = cKDTree(tex.position).query(states.points[ids])
        ref = cycles[tex.row[nearest], tex.col[nearest]]
        ours = sol.z[ids]
        bias.append(np.abs(ours.mean(0) / ref.mean(0) - 1).max())
        rmse.append(np.sqrt(np.mean((ours - ref) ** 2)) / ref.mean())
    # Cycles' noise in the mean over the floor points is far below the biases compared.
    noise = np.abs(refs[0] - refs[1]).mean() / cycles.mean() / np.sqrt(len(ids))
    assert noise < 0.1 * bias[1] + 1e-3
    assert bias[1] < 0.5 * bias[0], bias
    assert bias[1] < 0.03, bias
    assert rmse[1] < 0.8 * rmse[0], rmse
