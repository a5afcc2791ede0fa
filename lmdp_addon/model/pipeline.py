"""The LMDP stages as one call each, on :class:`~lmdp_addon.settings.Settings`.

The stages are named by what they hold: ``scene`` (the scene arrays) -> ``states`` (3.1.1) ->
``dynamics`` (3.1.2) -> ``lmdp`` (state costs, 3.1.3) -> ``solution`` (the desirability z,
3.1.4). Three steps compute them: :func:`run_sample` the states, :func:`run_build` the dynamics,
:func:`run_solve` the lmdp and the solution; :func:`run_all` runs the three and returns an
:class:`LMDPResult`. Operators, scripts and benchmarks call these; each step takes the previous
stages and an optional :class:`~lmdp_addon.progress.Progress`, and raises typed errors with user
messages.

Checks run once per call: :func:`check_build` estimates the build's memory before any work, in
:func:`run_build` and :func:`run_all` unless ``check=False`` (the operators check on Blender's
main thread and pass ``check=False`` to the worker).
"""
from dataclasses import dataclass, field

import numpy as np

from .costs import build_first_exit_lmdp, thesis_lambda
from .dynamics import build_passive_dynamics, check_budget
from ..errors import StageOrderError
from ..progress import Progress
from .solvers import solve_desirability
from .states import sample_states

#: What to tell the user when a stage is needed but missing.
MISSING_STAGE_MESSAGES = {
    "scene": "Sample the states first (LMDP > Sample States)",
    "states": "Sample the states first (LMDP > Sample States)",
    "dynamics": "Build the dynamics first (LMDP > Build Dynamics)",
    "lmdp": "Solve first (LMDP > Solve)",
    "solution": "Solve first (LMDP > Solve)",
}


@dataclass
class LMDPResult:
    """The stages of one scene; a later stage may still be None.

    scene     :class:`~lmdp_addon.scene_arrays.SceneArrays` the states were sampled on
    states    :class:`~lmdp_addon.model.states.StateSpace`
    dynamics  :class:`~lmdp_addon.model.dynamics.PassiveDynamics`
    lmdp      :class:`~lmdp_addon.model.costs.FirstExitLMDP` (state costs, P, z of the terminals)
    solution  :class:`~lmdp_addon.model.solvers.Solution`
    seconds   wall time of each step that ran: ``"sample"``, ``"build"``, ``"solve"``
    """

    scene: object
    states: object = None
    dynamics: object = None
    lmdp: object = None
    solution: object = None
    seconds: dict = field(default_factory=dict)

    def stages(self):
        """``{stage name: value}`` in pipeline order (None where the stage is missing)."""
        return {"scene": self.scene, "states": self.states, "dynamics": self.dynamics,
                "lmdp": self.lmdp, "solution": self.solution}

    def require(self, stage):
        """The value of ``stage`` (one of :data:`MISSING_STAGE_MESSAGES`); raises
        :class:`StageOrderError` with a user message when it is missing."""
        value = self.stages()[stage]
        if value is None:
            raise StageOrderError(MISSING_STAGE_MESSAGES[stage])
        return value


def _progress(progress):
    return progress if progress is not None else Progress()


def check_build(scene, settings, states=None):
    """Raise :class:`~lmdp_addon.errors.BudgetError` when building the dynamics would need more
    memory than ``settings.memory_budget_gb``; returns the estimate in bytes.

    Counts ``states.n_points`` x ``states.n_strata`` when the states are given, else
    ``settings.point_count`` x ``settings.strata_count`` (what :func:`run_sample` will sample),
    and the glossy points' directional unknowns (their BSDF rays and light samples).
    """
    if states is not None:
        n_points, n_strata = states.n_points, states.n_strata
        n_glossy = states.unknowns.n_glossy
    else:
        n_points, n_strata = settings.point_count, settings.strata_count
        n_glossy = glossy_point_estimate(scene, n_points)
    return check_budget(n_points, n_strata, settings.rays_per_stratum, settings.memory_budget_gb,
                        settings.light_samples, scene.n_triangles, n_glossy)


def glossy_point_estimate(scene, point_count):
    """How many of ``point_count`` points :func:`run_sample` puts on glossy triangles (their
    share of the state-carrying area, rounded up): they carry S unknowns each."""
    if not scene.has_glossy():
        return 0
    with scene.held():
        areas = scene.triangle_geometry()[1]
        carriers = scene.state_triangles()
        total = areas[carriers].sum()
        glossy = areas[carriers & scene.glossy_triangles()].sum()
    return int(np.ceil(point_count * glossy / total)) if total > 0 else 0


def run_sample(scene, settings, progress=None):
    """Sample the states on the selected meshes (thesis 3.1.1); returns ``(states, seconds)``."""
    progress = _progress(progress)
    progress.begin("sample")
    states = sample_states(scene, settings.point_count, settings.strata_u, settings.strata_v,
                           seed=settings.seed)
    seconds = progress.end(states.summary())
    return states, seconds


def run_build(scene, states, settings, progress=None, check=True):
    """Cast rays and build the passive dynamics (thesis 3.1.2); returns ``(dynamics, seconds)``.

    With ``check`` the memory estimate (:func:`check_build`) runs first.
    """
    if states is None:
        raise StageOrderError(MISSING_STAGE_MESSAGES["states"])
    if check:
        check_build(scene, settings, states)
    progress = _progress(progress)
    progress.begin("build")
    dynamics = build_passive_dynamics(scene, states, settings.rays_per_stratum, seed=settings.seed,
                                      progress=progress, light_samples=settings.light_samples)
    seconds = progress.end(dynamics.summary())
    return dynamics, seconds


def lambda_for(scene, settings):
    """λ of the THESIS cost mode: the thesis's default times ``lambda_scale`` (3.1.3)."""
    return thesis_lambda(scene.total_emitted_power_density(), settings.lambda_scale)


def run_solve(scene, states, dynamics, settings, progress=None):
    """State costs, then the desirability z (thesis 3.1.3-3.1.4); returns
    ``(lmdp, solution, seconds)``."""
    if dynamics is None:
        raise StageOrderError(MISSING_STAGE_MESSAGES["dynamics"])
    progress = _progress(progress)
    progress.begin("solve")
    lam = lambda_for(scene, settings) if settings.cost_mode == "THESIS" else None
    lmdp = build_first_exit_lmdp(dynamics, states, settings.cost_mode, lam, settings.epsilon)
    solution = solve_desirability(lmdp, settings.solver, settings.tolerance, settings.max_iterations,
                                  seed=settings.seed, progress=progress,
                                  memory_budget_gb=settings.memory_budget_gb)
    seconds = progress.end(solution.summary())
    return lmdp, solution, seconds


def run_all(scene, settings, progress=None, check=True):
    """Sample, build and solve; returns an :class:`LMDPResult` with each step's wall time.

    With ``check`` the memory estimate of the build (:func:`check_build`) runs before any work.
    """
    if check:
        check_build(scene, settings)
    result = LMDPResult(scene=scene)
    result.states, result.seconds["sample"] = run_sample(scene, settings, progress)
    result.dynamics, result.seconds["build"] = run_build(scene, result.states, settings, progress,
                                                         check=False)
    result.lmdp, result.solution, result.seconds["solve"] = run_solve(
        scene, result.states, result.dynamics, settings, progress)
    return result
