"""The LMDP stages as one call each, on :class:`~lmdp_addon.settings.Settings`.

Operators, scripts and benchmarks call these; each stage takes the previous stage's result and
an optional :class:`~lmdp_addon.progress.Progress`, and raises typed errors with user messages.
"""
from dataclasses import dataclass, field

import numpy as np

from .costs import build_first_exit_lmdp, thesis_lambda
from .dynamics import build_passive_dynamics, check_budget
from ..errors import StageOrderError
from .policy import stratum_policy
from ..progress import Progress
from .solvers import solve_desirability
from .states import sample_states


@dataclass
class LMDPResult:
    """Everything the stages produced for one scene (any later field may still be None)."""

    scene: object
    states: object = None
    dynamics: object = None
    lmdp: object = None
    solution: object = None
    seconds: dict = field(default_factory=dict)

    def require(self, stage):
        """Raise :class:`StageOrderError` unless ``stage`` ('states', 'dynamics', 'solution') exists."""
        messages = {
            "states": "Sample the states first (LMDP > Sample States)",
            "dynamics": "Build the dynamics first (LMDP > Build Dynamics)",
            "solution": "Solve first (LMDP > Solve)",
        }
        if getattr(self, stage if stage != "solution" else "solution") is None:
            raise StageOrderError(messages[stage])


def _progress(progress):
    return progress if progress is not None else Progress()


def run_sample(scene, settings, progress=None):
    """Stage 1 (thesis 3.1.1): sample the states on the selected meshes."""
    progress = _progress(progress)
    progress.begin("sample")
    states = sample_states(scene, settings.point_count, settings.strata_u, settings.strata_v,
                           seed=settings.seed)
    seconds = progress.end(states.summary())
    return states, seconds


def run_build(scene, states, settings, progress=None):
    """Stage 2 (thesis 3.1.2): cast rays and build the passive dynamics."""
    if states is None:
        raise StageOrderError("Sample the states first (LMDP > Sample States)")
    progress = _progress(progress)
    check_budget(states.n_points, states.n_strata, settings.rays_per_stratum, settings.memory_budget_gb,
                 settings.light_samples, scene.n_triangles)
    progress.begin("build")
    dynamics = build_passive_dynamics(scene, states, settings.rays_per_stratum, seed=settings.seed,
                                      progress=progress, memory_budget_gb=settings.memory_budget_gb,
                                      light_samples=settings.light_samples)
    seconds = progress.end(dynamics.summary())
    return dynamics, seconds


def lambda_for(scene, settings):
    """λ of the THESIS cost mode: the thesis's default times ``lambda_scale`` (3.1.3)."""
    return thesis_lambda(scene.total_emitted_power_density(), settings.lambda_scale)


def run_solve(scene, states, dynamics, settings, progress=None):
    """Stages 3-4 (thesis 3.1.3-3.1.4): state costs, then the desirability z."""
    if dynamics is None:
        raise StageOrderError("Build the dynamics first (LMDP > Build Dynamics)")
    progress = _progress(progress)
    progress.begin("solve")
    lam = lambda_for(scene, settings) if settings.cost_mode == "THESIS" else None
    lmdp = build_first_exit_lmdp(dynamics, states, settings.cost_mode, lam, settings.epsilon)
    solution = solve_desirability(lmdp, settings.solver, settings.tolerance, settings.max_iterations,
                                  seed=settings.seed, progress=progress,
                                  memory_budget_gb=settings.memory_budget_gb)
    seconds = progress.end(solution.summary())
    return lmdp, solution, seconds


def run_all(scene, settings, progress=None):
    """Sample, build and solve; returns an :class:`LMDPResult` with per-stage wall times."""
    result = LMDPResult(scene=scene)
    result.states, result.seconds["sample"] = run_sample(scene, settings, progress)
    result.dynamics, result.seconds["build"] = run_build(scene, result.states, settings, progress)
    result.lmdp, result.solution, result.seconds["solve"] = run_solve(
        scene, result.states, result.dynamics, settings, progress)
    return result


def directional_policy(result, columns="all"):
    """u*(k|x) of every point (m, S); see :func:`lmdp_addon.model.policy.stratum_policy`."""
    result.require("solution")
    return stratum_policy(result.dynamics, result.solution, columns)


def point_desirability(result):
    """(m, C) z of every point, with C = 1 (THESIS) or 3 (PHYSICAL)."""
    result.require("solution")
    return np.asarray(result.solution.z)
