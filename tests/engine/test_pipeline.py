"""The stage calls of lmdp_addon.model.pipeline: one memory check per call, stage names."""
import numpy as np
import pytest

from lmdp_addon.demo_geometry import build_scene_arrays
from lmdp_addon.errors import BudgetError, StageOrderError
from lmdp_addon.model import dynamics, pipeline
from lmdp_addon.progress import Progress
from lmdp_addon.settings import Settings

SMALL = dict(point_count=200, rays_per_stratum=2, light_samples=4)


class Recorder(Progress):
    def __init__(self):
        super().__init__()
        self.begun = []

    def begin(self, step):
        self.begun.append(step)
        super().begin(step)


@pytest.fixture
def estimates(monkeypatch):
    """Counts the calls of the build's memory estimate (every check goes through it)."""
    calls = []
    original = dynamics.estimate_build_bytes

    def counted(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(dynamics, "estimate_build_bytes", counted)
    return calls


def test_check_build_counts_the_states_when_given_else_the_settings():
    scene = build_scene_arrays("CORNELL_BOX")
    settings = Settings(point_count=1000, strata_u=4, strata_v=2, rays_per_stratum=2, light_samples=4)
    expect = dynamics.estimate_build_bytes(1000, 8, 2, 4, scene.n_triangles)
    assert pipeline.check_build(scene, settings) == expect
    states, _ = pipeline.run_sample(scene, Settings(**SMALL))
    assert pipeline.check_build(scene, settings, states) == dynamics.estimate_build_bytes(
        200, 16, 2, 4, scene.n_triangles)
    with pytest.raises(BudgetError, match=r"GiB.*budget"):
        pipeline.check_build(scene, Settings(**SMALL, memory_budget_gb=expect / 4 / 1024 ** 3))


def test_run_all_checks_once_before_any_work(estimates):
    scene = build_scene_arrays("CORNELL_BOX")
    result = pipeline.run_all(scene, Settings(**SMALL))
    assert len(estimates) == 1
    assert result.solution is not None and set(result.seconds) == {"sample", "build", "solve"}
    progress = Recorder()
    with pytest.raises(BudgetError):
        pipeline.run_all(scene, Settings(**SMALL, memory_budget_gb=1e-6), progress)
    assert progress.begun == []                   # refused before sampling


def test_run_build_checks_once_unless_told_not_to(estimates):
    scene = build_scene_arrays("CORNELL_BOX")
    settings = Settings(**SMALL)
    states, _ = pipeline.run_sample(scene, settings)
    pipeline.run_build(scene, states, settings)
    assert len(estimates) == 1
    tiny = Settings(**SMALL, memory_budget_gb=1e-6)
    with pytest.raises(BudgetError):
        pipeline.run_build(scene, states, tiny)
    del estimates[:]
    dyn, _ = pipeline.run_build(scene, states, tiny, check=False)      # the caller checked
    assert estimates == [] and dyn.n_points == 200


def test_build_passive_dynamics_checks_only_when_given_a_budget(estimates):
    scene = build_scene_arrays("CORNELL_BOX")
    states, _ = pipeline.run_sample(scene, Settings(**SMALL))
    dynamics.build_passive_dynamics(scene, states, 2, light_samples=4)
    assert estimates == []
    dynamics.build_passive_dynamics(scene, states, 2, light_samples=4, memory_budget_gb=8.0)
    assert len(estimates) == 1


def test_result_requires_its_stages_by_name():
    scene = build_scene_arrays("CORNELL_BOX")
    empty = pipeline.LMDPResult(scene=scene)
    assert empty.require("scene") is scene
    for stage, message in (("states", "Sample"), ("dynamics", "Build"), ("lmdp", "Solve"),
                           ("solution", "Solve")):
        with pytest.raises(StageOrderError, match=message):
            empty.require(stage)
    result = pipeline.run_all(scene, Settings(**SMALL))
    assert list(result.stages()) == ["scene", "states", "dynamics", "lmdp", "solution"]
    assert result.require("lmdp") is result.lmdp
    assert np.all(np.isfinite(result.require("solution").z))
    with pytest.raises(StageOrderError, match="Sample"):
        pipeline.run_build(scene, None, Settings(**SMALL))
    with pytest.raises(StageOrderError, match="Build"):
        pipeline.run_solve(scene, result.states, None, Settings(**SMALL))
