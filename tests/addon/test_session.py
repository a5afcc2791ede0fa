"""The per-scene session store: stage dependencies, scene identity, clearing on file load."""
import bpy
import numpy as np
import pytest
import scipy.sparse


class FakeStates:
    """A stand-in engine result with the counts the status lines describe."""

    def __init__(self, n_points):
        self.n_points = n_points
        self.points = np.zeros((n_points, 3))


def test_downstream_follows_the_pipeline(lmdp_ext):
    session = lmdp_ext.sub("operators.session")
    assert session.downstream("scene") == list(session.STAGES)
    assert session.downstream("states") == ["states", "dynamics", "lmdp", "solution", "policy",
                                            "display", "bake"]
    assert session.downstream("solution") == ["solution", "policy", "display", "bake"]
    assert session.downstream("bake") == ["bake"]
    with pytest.raises(KeyError):
        session.downstream("no_such_stage")


def test_storing_a_stage_invalidates_what_was_computed_from_it(fresh_scene, lmdp_ext):
    session = lmdp_ext.sub("operators.session").session_for(fresh_scene)
    for stage in ("scene", "states", "dynamics", "solution", "bake"):
        session.store(stage, object(), seconds=1.0)
    session.store("states", FakeStates(10), seconds=0.5)
    assert session.has("scene") and session.has("states")
    assert not session.has("dynamics") and not session.has("solution") and not session.has("bake")
    assert set(session.timings) == {"scene", "states"}
    assert session.invalidate_from("scene") == ["scene", "states"]
    assert session.results == {}


def test_require_names_the_missing_stage(fresh_scene, lmdp_ext):
    errors = lmdp_ext.sub("lmdp_addon.errors")
    session = lmdp_ext.sub("operators.session").session_for(fresh_scene)
    with pytest.raises(errors.StageOrderError, match="Build the dynamics first"):
        session.require("dynamics")
    with pytest.raises(errors.StageOrderError, match="Solve first"):
        session.require("solution")
    session.store("dynamics", "P")
    assert session.require("dynamics") == "P"


def test_session_follows_a_renamed_scene_but_not_a_copy(fresh_scene, lmdp_ext):
    store = lmdp_ext.sub("operators.session")
    assert store.peek(fresh_scene) is None
    session = store.session_for(fresh_scene)
    session.store("states", FakeStates(5))
    fresh_scene.name = "Renamed"
    assert store.peek(fresh_scene) is session
    copy = fresh_scene.copy()
    assert copy.lmdp.session_id == fresh_scene.lmdp.session_id  # Blender copies the property
    assert store.peek(copy) is None
    copy_session = store.session_for(copy)
    assert copy_session is not session and not copy_session.has("states")
    assert copy.lmdp.session_id != fresh_scene.lmdp.session_id
    assert store.peek(fresh_scene) is session


def test_loading_a_file_drops_every_session(fresh_scene, lmdp_ext):
    store = lmdp_ext.sub("operators.session")
    store.session_for(fresh_scene).store("states", FakeStates(3))
    assert store.all_sessions()
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    assert store.all_sessions() == {}
    assert store.peek(bpy.context.scene) is None


def test_status_lines_count_and_measure(fresh_scene, lmdp_ext):
    store = lmdp_ext.sub("operators.session")
    session = store.session_for(fresh_scene)
    session.store("states", FakeStates(1000), seconds=0.25)
    stage, text = session.status_lines()[0]
    assert stage == "states"
    assert "1,000 points" in text and "23.4 KiB" in text and "250 ms" in text
    session.note("states", "Sampled 1000 points")
    assert session.last_message == "Sampled 1000 points"


def test_result_nbytes_counts_sparse_matrices(lmdp_ext):
    store = lmdp_ext.sub("operators.session")

    class Dynamics:
        def __init__(self):
            self.P = scipy.sparse.identity(100, format="csr", dtype=np.float32)

    P = Dynamics().P
    expected = P.data.nbytes + P.indices.nbytes + P.indptr.nbytes
    assert store.result_nbytes(Dynamics()) == expected
