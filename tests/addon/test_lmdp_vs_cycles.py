"""PHYSICAL-mode z is the discrete light transport solution: refining the state space brings it
closer to Cycles' bake of the same scene (issue 3, Accuracy)."""
import numpy as np
from scipy.spatial import cKDTree


def floor_texels(ext, scene_arrays, resolution):
    texels = ext.sub("lmdp_addon.bake.texels")
    floor = scene_arrays.object_names.index("Floor")
    tris = np.flatnonzero(scene_arrays.triangle_object == floor)
    normals, _ = scene_arrays.triangle_geometry()
    return texels.rasterize_texels(scene_arrays.triangle_uv[tris], scene_arrays.corners()[tris],
                                   normals[tris], resolution)


def test_refinement_converges_towards_cycles(lmdp_ext, fresh_scene):
    """The floor's outgoing radiance z (albedo x irradiance / π, PHYSICAL mode) at every floor
    state against Cycles' DIFFUSE bake with DIRECT + INDIRECT + COLOR at the texel containing the
    state. The LMDP's discretisation error (piecewise-constant radiance of the states a ray
    lands in, noisy transitions) must be small and shrink as points are added: the mean bias
    stays within 3 % (buried states get no light: ``locator.buried_points``) and the per-point
    error falls. Cycles' own noise is estimated from two seeds."""
    import bpy
    demo = lmdp_ext.sub("operators.adapters.demo_scenes")
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
        arrays, states, sol = sess.require("scene"), sess.require("states"), sess.require("solution")
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
    assert max(bias) < 0.03, bias
    # The per-point error less Cycles' own per-texel noise (the mean of two seeds: half the
    # squared difference of the seeds, halved again) is the LMDP's, and it falls, slowly: most
    # of it is each point's own Monte Carlo noise, 64 rays per point at any count.
    texel_noise2 = np.mean((refs[0] - refs[1]) ** 2) / 4 / cycles.mean() ** 2
    own = np.sqrt(np.maximum(np.square(rmse) - texel_noise2, 0.0))
    assert own[1] < own[0], (rmse, np.sqrt(texel_noise2))
