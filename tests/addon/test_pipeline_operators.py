"""The pipeline operators as a user runs them: bpy.ops on a real scene, results in the session."""
import numpy as np
import pytest
import scipy.sparse as sp


@pytest.fixture
def cornell(fresh_scene):
    import bpy
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    settings = fresh_scene.lmdp
    settings.point_count = 600
    settings.rays_per_stratum = 2
    settings.cost_mode = 'PHYSICAL'
    return fresh_scene


def session(lmdp_ext, scene):
    return lmdp_ext.sub("operators.session").session_for(scene)


def test_stages_in_order_fill_the_session(lmdp_ext, cornell):
    import bpy
    s = session(lmdp_ext, cornell)
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    states = s.require("states")
    assert states.n_points == 600 and states.n_strata == 16
    assert set(s.object_names) == {o.name for o in bpy.context.selected_objects}
    assert bpy.ops.lmdp.build_dynamics() == {'FINISHED'}
    dyn = s.require("dynamics")
    assert dyn.rays == 600 * 16 * 2 and dyn.n_emitters == 1
    assert dyn.counts["nee_rays"] == 600 * cornell.lmdp.light_samples
    sums = np.asarray(dyn.P.sum(axis=1)).ravel()  # one in expectation (next-event estimation)
    assert abs(sums.mean() - 1) < 5 * sums.std() / np.sqrt(len(sums))
    assert bpy.ops.lmdp.solve() == {'FINISHED'}
    sol = s.require("solution")
    assert sol.converged and sol.z.shape == (600, 3) and np.all(sol.z[sol.reachable] > 0)
    # Re-sampling invalidates everything computed from the old states.
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    assert not s.has("dynamics") and not s.has("solution")


def test_stages_out_of_order_are_refused_and_change_nothing(lmdp_ext, cornell, capsys):
    import bpy
    s = session(lmdp_ext, cornell)
    with pytest.raises(RuntimeError, match="Sample the states first"):
        bpy.ops.lmdp.build_dynamics()
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    with pytest.raises(RuntimeError, match="Build the dynamics first"):
        bpy.ops.lmdp.solve()
    assert s.has("states") and not s.has("dynamics")
    with pytest.raises(RuntimeError, match="Solve first"):
        bpy.ops.lmdp.export_npz(filepath="/tmp/never.npz")


def test_memory_budget_refuses_before_any_work(lmdp_ext, cornell):
    import bpy
    s = session(lmdp_ext, cornell)
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    cornell.lmdp.memory_budget_gb = 0.001
    cornell.lmdp.rays_per_stratum = 256
    with pytest.raises(RuntimeError, match=r"would need about .* GiB, above the memory budget"):
        bpy.ops.lmdp.build_dynamics()
    assert not s.has("dynamics") and s.has("states")


def test_no_light_anywhere_is_refused(lmdp_ext, cornell):
    import bpy
    light = bpy.data.objects["Light"]
    bpy.data.objects.remove(light)
    s = session(lmdp_ext, cornell)
    with pytest.raises(RuntimeError, match="no light"):
        bpy.ops.lmdp.sample_states()
    assert not s.has("states")


def test_run_pipeline_and_export_npz(lmdp_ext, cornell, tmp_path):
    import bpy
    s = session(lmdp_ext, cornell)
    cornell.lmdp.cost_mode = 'THESIS'
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    sol = s.require("solution")
    assert sol.cost_mode == "THESIS" and sol.converged
    path = tmp_path / "cornell.npz"
    assert bpy.ops.lmdp.export_npz(filepath=str(path)) == {'FINISHED'}
    f = np.load(path)
    P = sp.csr_matrix((f["P_data"], f["P_indices"], f["P_indptr"]), shape=tuple(f["P_shape"]))
    m = P.shape[0]
    assert m == cornell.lmdp.point_count
    z = f["z"]
    assert np.allclose(z[:m], f["q"][:m] * (P @ z), rtol=1e-8, atol=1e-300)
    assert str(f["cost_mode"]) == "THESIS" and float(f["lambda_"]) > 1.0


def test_export_to_output_dir_and_missing_folder(lmdp_ext, cornell, tmp_path):
    import bpy
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    cornell.lmdp.output_dir = str(tmp_path)
    assert bpy.ops.lmdp.export_npz() == {'FINISHED'}
    assert (tmp_path / "lmdp.npz").exists()
    with pytest.raises(RuntimeError, match="does not exist"):
        bpy.ops.lmdp.export_npz(filepath=str(tmp_path / "missing" / "x.npz"))
