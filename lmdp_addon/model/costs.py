"""State costs and the first-exit LMDP (thesis 3.1.3, 3.1.4).

The first-exit LMDP (Todorov 2009) splits the states into non-terminal N (the surface points)
and terminal T (emitters, world, void, lamps) and asks for the desirability

    z_N = Q_N (P_NN z_N + P_NT z_T),      Q = diag(exp(-λ g)),          (eq. 2.22, first exit)

with z_T fixed. Two cost modes build Q, P and z_T (see ``design.md``):

* ``THESIS``  : P normalised with the ε self-loop of eq. 3.1; g = 1 on points, 0 on emitters;
                z_T = 1 on emitters and lamps (and a non-black world; per direction bin of an
                environment map its luminance relative to the brightest bin), 0 on the void;
                λ = thesis default (sum of the lights' power per unit area) x ``lambda_scale``.
* ``PHYSICAL``: P = cosine-weighted form factors; Q = diag(albedo) per RGB channel (g = -log
                albedo, λ = 1; a glossy unknown (x, k) takes its directional albedo a_k, the
                BSDF's ∫ f(ω_i, ω_k) cos θ_i dω_i, and P its BSDF rows normalised to one,
                ``dynamics.py``); z_T = emitted radiance (a lamp's ``Lamps.emission``, which its
                light samples' mass turns into its direct light, see ``lamps.py``). Then the
                equation above *is* the discretised light transport equation (eq. 2.7): z_N is
                the outgoing radiance.
"""
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import SceneError
from ..scene_arrays import luminance
from ..settings import COST_MODES


@dataclass
class FirstExitLMDP:
    """The linear problem ``z_N = q ⊙ (P_NN z_N + P_NT z_T)``, per channel.

    P          CSR (m, m + nT) float64 passive dynamics used by the solve (with the ε self-loop
               in THESIS mode); columns as in :class:`~lmdp_addon.model.dynamics.PassiveDynamics`
    q          (m, C) diagonal of Q on the non-terminal states (C = 1 THESIS, 3 PHYSICAL)
    z_terminal (nT, C) fixed desirability of the terminal states
    lambda_    λ (1 in PHYSICAL mode)
    cost_mode  'THESIS' or 'PHYSICAL'
    g          (m, C) state cost of the non-terminal states, ``q = exp(-λ g)``
    """

    P: sp.csr_matrix
    q: np.ndarray
    z_terminal: np.ndarray
    lambda_: float
    cost_mode: str
    g: np.ndarray
    epsilon: float = 0.0

    @property
    def n_points(self):
        return self.P.shape[0]

    @property
    def n_channels(self):
        return self.q.shape[1]

    @property
    def log_q(self):
        """(m, C) ``log q = -λ g``, exact where q itself underflows (large λ)."""
        return -self.lambda_ * np.asarray(self.g, dtype=np.float64)

    @property
    def P_NN(self):
        return self.P[:, :self.n_points]

    @property
    def P_NT(self):
        return self.P[:, self.n_points:]

    def terminal_drive(self):
        """``P_NT z_T`` (m, C): what the terminals contribute in one transition."""
        return np.asarray(self.P_NT @ self.z_terminal).reshape(self.n_points, self.n_channels)


def thesis_lambda(scene_power_density, lambda_scale):
    """The thesis's λ (3.1.3): sum over lights of their power per unit area, times a scale."""
    return float(scene_power_density) * float(lambda_scale)


def build_first_exit_lmdp(dynamics, states, cost_mode="PHYSICAL", lambda_=None, epsilon=5e-5):
    """Assemble Q, P and z_T of the first-exit LMDP for ``cost_mode`` (module docstring).

    ``lambda_`` is required in THESIS mode (see :func:`thesis_lambda`); it is ignored (λ = 1) in
    PHYSICAL mode.
    """
    if cost_mode not in COST_MODES:
        raise SceneError(f"Unknown cost mode {cost_mode!r}: use one of {', '.join(COST_MODES)}")
    m = dynamics.n_unknowns
    E = dynamics.n_emitters
    P = sp.csr_matrix(dynamics.P, dtype=np.float64)
    if cost_mode == "THESIS":
        if lambda_ is None or not np.isfinite(lambda_) or lambda_ <= 0:
            raise SceneError(f"λ must be a positive finite number in THESIS mode (got {lambda_}); "
                             "check Lambda Scale and that the scene has a light")
        eps = float(epsilon)
        # eq. 3.1: ε self-loop keeps the chain aperiodic; renormalise each row to sum to one.
        P = P + sp.csr_matrix((np.full(m, eps), (np.arange(m), np.arange(m))), shape=P.shape)
        rows = np.asarray(P.sum(axis=1)).reshape(-1)
        P = sp.diags(1.0 / np.where(rows > 0, rows, 1.0)) @ P
        g = np.ones((m, 1))
        q = np.exp(-lambda_ * g)
        world = luminance(dynamics.world_terminal_radiance())
        # 1 on a lit uniform world; per direction bin its luminance relative to the brightest
        world_z = world / world.max() if world.max() > 0 else np.zeros_like(world)
        z_terminal = np.concatenate([np.ones(E), world_z, [0.0], np.ones(dynamics.n_lamps)]).reshape(-1, 1)
        lam = float(lambda_)
    else:
        eps = 0.0
        albedo = np.clip(unknown_albedo(dynamics, states), 0.0, 1.0)
        q = albedo
        with np.errstate(divide="ignore"):
            g = -np.log(albedo)
        z_terminal = np.vstack([dynamics.emitter_radiance.reshape(E, 3),
                                dynamics.world_terminal_radiance(), np.zeros((1, 3)),
                                dynamics.lamp_radiance.reshape(-1, 3)])
        lam = 1.0
    return FirstExitLMDP(P=sp.csr_matrix(P), q=q, z_terminal=z_terminal, lambda_=lam,
                         cost_mode=cost_mode, g=g, epsilon=eps)


def unknown_albedo(dynamics, states):
    """(N, 3) the albedo of every unknown: a Lambertian point's ``point_albedo``, a glossy
    unknown's directional albedo a_k (``PassiveDynamics.glossy_albedo``)."""
    albedo = np.asarray(states.point_albedo, dtype=np.float64)
    u = dynamics.unknown_map
    if u.identity:
        return albedo
    out = albedo[u.point].copy()
    out[u.stratum >= 0] = dynamics.glossy_albedo
    return out


def scalar_desirability(values):
    """One number per state from (n, C) values: the value itself, or Rec.709 luminance of RGB."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        return values
    if values.shape[1] == 1:
        return values[:, 0]
    return luminance(values)
