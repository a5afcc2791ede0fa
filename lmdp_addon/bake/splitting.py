"""Russian roulette and splitting driven by the solution: paths spend rays where light will come from.

The solved desirability is the expected light of a path's future (thesis eq. 2.22, PHYSICAL
costs: z is the outgoing radiance of the states). A path at its vertex y_k with throughput β_k
will still collect about

    β_k V(y_k),      V(s) = P_NN z_N + P_NW z_W      (the light arriving at state s, luminance)

of an estimate whose mean is I(x_0) ≈ V(s_0). Their ratio ``r = lum(β_k) V(y_k) / V(s_0)`` is
the share of the answer still ahead of the path (adjoint-driven Russian roulette and splitting,
Vorba & Křivánek 2016). A weight window on r keeps every path near one share:

* ``r > 1`` (a path of the dim room that has just passed the hatch into the lit one): the path
  is split into ``n = ⌊r + u⌋`` copies (at most :data:`MAX_COPIES`), each with β / n, each
  continuing on its own random numbers;
* ``r < 1`` from the Russian-roulette vertex on: the path survives with ``max(r, floor)`` and
  its β is divided by that.

Both keep the estimate unbiased whatever V is: the copies' mean and the survivors' weight have
the path's expectation for any n and survival probability drawn independently of the path's
future. V only decides where rays go; a poor V costs efficiency, never correctness. Vertices or
texels without a compatible state keep the tracer's throughput roulette.

* :class:`SplitField`: V at the states and their lookup, from a solved LMDP;
* :func:`window`: the survivals and copy counts of a wavefront.
"""
from dataclasses import dataclass

import numpy as np

from .fine_guide import incoming_radiance_source
from .guide import guide_frame, locate_hits, locate_points, neighbour_average

#: Most copies one vertex is split into (a bound on one wavefront's growth).
MAX_COPIES = 2
#: Smallest survival probability of the solution's roulette (V can be too low where the solve
#: saw little light: a floor keeps such paths from carrying huge weights).
SURVIVAL_FLOOR = 0.1
#: States whose V is averaged into each state's (the rays' noise of one row of P).
SPLIT_NEIGHBOURS = 8
#: The share of the answer a path should carry (the window's centre, in units of V(s_0)).
WINDOW = 1.0


@dataclass
class SplitField:
    """V (m,) float64 at the solved states and the lookup of the states of points and hits
    (``guide.guide_frame``: the build's locator, objects matched by name on another scene)."""

    value: np.ndarray
    locator: object
    same_scene: bool = True
    object_map: np.ndarray = None

    @classmethod
    def from_lmdp(cls, scene, lmdp):
        """The field of a solved ``lmdp`` (PHYSICAL costs) for tracing ``scene``."""
        locator, object_map, same = guide_frame(scene, lmdp)
        v = incoming_radiance_source(lmdp)
        v = neighbour_average(v[:, None], locator, lmdp.states.normals, SPLIT_NEIGHBOURS)[:, 0]
        return cls(value=np.maximum(v, 0.0), locator=locator, same_scene=same, object_map=object_map)

    def at_states(self, states):
        """V of ``states`` (k,) (0 where -1: no compatible state)."""
        states = np.asarray(states)
        return np.where(states >= 0, np.take(self.value, np.maximum(states, 0)), 0.0)

    def at_points(self, positions, side_normals, objects):
        """V at arbitrary surface points (the texels)."""
        return self.at_states(locate_points(self.locator, self.object_map, positions, side_normals, objects))

    def states_at_hits(self, tri, bu, bv, positions, side_normals, front, objects):
        """The states of ray hits (-1: none), as the guide finds them (``guide.locate_hits``)."""
        return locate_hits(self.locator, self.same_scene, self.object_map, tri, bu, bv, positions, side_normals,
                           front, objects)


def window(ratio, known, roulette, rng):
    """``(survival p (k,), copies n (k,))`` of the weight window on ``ratio`` r (k,) where
    ``known`` (V at the vertex and the texel); ``roulette`` (k,) bool: where the solution's
    roulette may end the path. Rows not ``known`` get p = 1, n = 1 (the caller's roulette)."""
    k = len(ratio)
    ratio = ratio / WINDOW
    u = rng.random(k)
    copies = np.ones(k, np.int64)
    split = known & (ratio > 1.0)
    copies[split] = np.minimum(np.floor(ratio[split] + u[split]), MAX_COPIES).astype(np.int64)
    p = np.ones(k)
    low = known & roulette & (ratio < 1.0)
    p[low] = np.maximum(ratio[low], SURVIVAL_FLOOR)
    return p, copies
