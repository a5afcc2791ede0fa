"""Hit classification (thesis 3.1.2): the next state each traced ray lands in.

A closest hit becomes a column of the passive dynamics (see
:class:`~lmdp_addon.model.dynamics.PassiveDynamics`): a front hit on a state-carrying surface
goes to the nearest compatible state point (:class:`~lmdp_addon.model.locator.StateLocator`), a
hit on an emitter to its emitter terminal, a miss to the world terminal (its direction bin's
under an environment map, the void under a black world), and everything else to the void.
"""
import numpy as np

from ..world import bin_of_direction, world_bin_count


class HitClassifier:
    """Per-triangle lookup tables that turn closest hits into next-state columns.

    Columns: ``0..m-1`` points, ``m..m+E-1`` emitter terminals, ``m+E..m+E+W-1`` world (W = 1,
    or one per direction bin of an environment map: ``world.bin_of_direction``), ``m+E+W`` void.
    """

    def __init__(self, scene, locator, n_points):
        self.scene = scene
        self.locator = locator
        tri_emitter, emitter_radiance = scene.emitter_groups()
        E = len(emitter_radiance)
        self.n_points = n_points
        env = getattr(scene, "environment", None)
        self.environment = env if env is not None and env.lit else None
        W = world_bin_count(self.environment)
        self.world_col = n_points + E
        self.void_col = n_points + E + W
        self.world_lit = bool(np.any(scene.world_radiance > 0))
        carries = scene.object_carries_states[scene.triangle_object] & (tri_emitter < 0)
        # Column of a front hit for every triangle (-1: carrier, look the point up), plus a
        # sentinel row T for misses. The back of a face carries no states: a ray that meets it
        # comes from inside a solid or sees a one-sided surface from behind, and goes to the void
        # (a lookup would hand it to the nearest state facing its way, through the solid: the
        # far side of a wall).
        front = np.where(tri_emitter >= 0, n_points + tri_emitter, np.where(carries, -1, self.void_col))
        back = np.where((tri_emitter >= 0) & scene.triangle_emission_two_sided, n_points + tri_emitter,
                        self.void_col)
        miss = self.world_col if self.world_lit else self.void_col
        self.front_col = np.append(front, miss).astype(np.int64)
        self.back_col = np.append(back, miss).astype(np.int64)
        self.normals = np.vstack([locator.face_normals, np.zeros((1, 3))]).astype(np.float32)
        self.is_emitter = np.append(tri_emitter >= 0, False)
        self.carries = np.append(carries, False)

    def classify(self, origins, directions, tri, dist, bary_u, bary_v, workers=-1):
        """Next-state column of every ray and a count per landing category."""
        T = self.scene.n_triangles
        t = np.where(tri >= 0, tri, T)
        front = np.einsum("ij,ij->i", np.take(self.normals, t, axis=0), directions) < 0.0
        col = np.where(front, np.take(self.front_col, t), np.take(self.back_col, t))
        if self.environment is not None:   # directional world terminals: the escape's bin
            miss = np.flatnonzero(tri < 0)
            col[miss] = self.world_col + bin_of_direction(directions[miss])
        n_miss = int(np.count_nonzero(tri < 0))
        counts = {"world": n_miss if self.world_lit else 0,
                  "void_escape": 0 if self.world_lit else n_miss}
        emitter = self.is_emitter[t]
        counts["emitters"] = int(np.count_nonzero(emitter & (col != self.void_col)))
        counts["void_emitter_back"] = int(np.count_nonzero(emitter & (col == self.void_col)))
        fl = np.flatnonzero(col < 0)                    # front hits on carriers
        pos = None
        if self.locator.exact:
            pos = origins[fl] + directions[fl] * dist[fl, None]
        col[fl] = self.locator.locate_front(t[fl], bary_u[fl], bary_v[fl], pos, workers=workers)
        counts["back_faces"] = int(np.count_nonzero(~front & self.carries[t]))
        unresolved = col < 0
        counts["void_no_state"] = int(np.count_nonzero(unresolved))
        col[unresolved] = self.void_col
        counts["points"] = int(np.count_nonzero(col < self.n_points))
        counts["void_unmodelled"] = int(np.count_nonzero(~emitter & ~self.carries[t] & (tri >= 0)))
        counts["void"] = int(np.count_nonzero(col == self.void_col))
        return col, counts
