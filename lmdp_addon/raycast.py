"""Ray casting with embreex (Embree 4): batched closest-hit and occlusion queries.

All queries take large numpy batches; the ray origin is offset along the geometric normal by the
caller (see :func:`offset_origins`) to avoid self-intersection.
"""
import numpy as np

from .errors import SceneError

#: Rays per embreex call: large enough to amortise the call, small enough for memory.
BATCH = 1 << 20


class RayCaster:
    """Embree scene of all valid triangles of a :class:`~lmdp_addon.scene.SceneArrays`.

    ``intersect`` returns the hit triangle (index into the *scene's* triangles, -1 for a miss) and
    the hit distance. Degenerate / non-finite triangles are left out of the BVH.
    """

    def __init__(self, scene):
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError as exc:  # pragma: no cover - depends on the installation
            raise SceneError(
                "The embreex ray tracer is not available (it ships for Linux x64, Windows x64 and "
                f"macOS arm64): {exc}") from exc
        self.scene = scene
        valid = np.flatnonzero(scene.valid_triangles())
        if len(valid) == 0:
            raise SceneError("The scene has no triangles with non-zero area to trace rays against")
        self.triangle_ids = valid.astype(np.int64)
        corners = scene.corners()[valid].astype(np.float32)
        self._embree = rtcore_scene.EmbreeScene()
        TriangleMesh(self._embree, np.ascontiguousarray(corners))
        self.scale = scene.bounding_diagonal()
        self.rays_cast = 0

    def intersect(self, origins, directions, barycentrics=False):
        """Closest hits: ``(triangle (n,) int64 or -1, distance (n,) float32 or inf)``.

        With ``barycentrics=True`` also the hit's barycentric ``u, v`` (weights of the
        triangle's second and third corner).
        """
        n = len(origins)
        tri = np.empty(n, dtype=np.int64)
        dist = np.empty(n, dtype=np.float32)
        if barycentrics:
            bu = np.empty(n, dtype=np.float32)
            bv = np.empty(n, dtype=np.float32)
        for start in range(0, n, BATCH):
            stop = min(start + BATCH, n)
            o = np.ascontiguousarray(origins[start:stop], dtype=np.float32)
            d = np.ascontiguousarray(directions[start:stop], dtype=np.float32)
            res = self._embree.run(o, d, output=1)
            prim = res["primID"].astype(np.int64)
            hit = prim >= 0
            tri[start:stop] = np.where(hit, self.triangle_ids[np.where(hit, prim, 0)], -1)
            dist[start:stop] = np.where(hit, res["tfar"], np.inf)
            if barycentrics:
                bu[start:stop] = res["u"]
                bv[start:stop] = res["v"]
        self.rays_cast += n
        if barycentrics:
            return tri, dist, bu, bv
        return tri, dist

    def occluded(self, origins, directions, distances):
        """True where something blocks the segment ``origin + t·direction, 0 < t < distance``."""
        n = len(origins)
        out = np.empty(n, dtype=bool)
        for start in range(0, n, BATCH):
            stop = min(start + BATCH, n)
            o = np.ascontiguousarray(origins[start:stop], dtype=np.float32)
            d = np.ascontiguousarray(directions[start:stop], dtype=np.float32)
            t = np.ascontiguousarray(distances[start:stop], dtype=np.float32)
            out[start:stop] = self._embree.run(o, d, dists=t, query="OCCLUDED") >= 0
        self.rays_cast += n
        return out

    def offset(self):
        """Origin offset along the normal, relative to the scene size (metres)."""
        return 1e-5 * self.scale


def offset_origins(points, normals, directions, eps):
    """Move ray origins off the surface, to the side the rays leave from (avoids self-hits)."""
    side = np.sign(np.einsum("ij,ij->i", normals, directions))[:, None]
    side[side == 0] = 1.0
    return points + eps * side * normals
