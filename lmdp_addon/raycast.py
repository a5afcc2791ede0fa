"""Ray casting with embreex (Embree 4): batched closest-hit and occlusion queries.

All queries take large numpy batches; the caller offsets the ray origin along the normal by
:meth:`RayCaster.offset` to avoid self-intersection.
"""
import numpy as np

from .errors import SceneError

#: Rays per embreex call: large enough to amortise the call, small enough for memory.
BATCH = 1 << 20


class RayCaster:
    """Embree scene of all valid triangles of a :class:`~lmdp_addon.scene_arrays.SceneArrays`.

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
        self._identity = len(valid) == scene.n_triangles   # embree's primID is the triangle
        # Shared vertices and an index buffer: embreex copies its input element by element, and
        # a vertex list is about half the size of three corners per triangle. The valid
        # triangles only use finite vertices; the others are zeroed.
        vertices = np.where(np.isfinite(scene.vertices), scene.vertices, 0.0).astype(np.float32)
        self._embree = rtcore_scene.EmbreeScene()
        TriangleMesh(self._embree, vertices, np.ascontiguousarray(scene.triangles[valid], dtype=np.int32))
        self.scale = scene.bounding_diagonal()
        self.rays_cast = 0

    def intersect(self, origins, directions, barycentrics=False):
        """Closest hits: ``(triangle (n,) int64 or -1, distance (n,) float32 or inf)``.

        With ``barycentrics=True`` also the hit's barycentric ``u, v`` (weights of the
        triangle's second and third corner).
        """
        n = len(origins)
        chunks = []
        for start in range(0, n, BATCH):
            stop = min(start + BATCH, n)
            o = np.ascontiguousarray(origins[start:stop], dtype=np.float32)
            d = np.ascontiguousarray(directions[start:stop], dtype=np.float32)
            res = self._embree.run(o, d, output=1)
            prim = res["primID"]                       # -1 for a miss
            hit = prim >= 0
            if self._identity:
                tri = prim.astype(np.int64)
            else:
                tri = np.where(hit, np.take(self.triangle_ids, np.maximum(prim, 0)), -1)
            dist = np.where(hit, res["tfar"], np.float32(np.inf))
            chunks.append((tri, dist, res["u"], res["v"]) if barycentrics else (tri, dist))
        self.rays_cast += n
        if len(chunks) == 1:
            return chunks[0]
        if not chunks:
            empty = (np.zeros(0, np.int64), np.zeros(0, np.float32))
            return empty + (np.zeros(0, np.float32),) * 2 if barycentrics else empty
        return tuple(np.concatenate(parts) for parts in zip(*chunks))

    def occluded(self, origins, directions, distances):
        """True where something blocks the segment ``origin + t·direction, 0 < t < distance``."""
        n = len(origins)
        chunks = []
        for start in range(0, n, BATCH):
            stop = min(start + BATCH, n)
            o = np.ascontiguousarray(origins[start:stop], dtype=np.float32)
            d = np.ascontiguousarray(directions[start:stop], dtype=np.float32)
            t = np.ascontiguousarray(distances[start:stop], dtype=np.float32)
            chunks.append(self._embree.run(o, d, dists=t, query="OCCLUDED") >= 0)
        self.rays_cast += n
        if len(chunks) == 1:
            return chunks[0]
        return np.concatenate(chunks) if chunks else np.zeros(0, dtype=bool)

    def offset(self):
        """Origin offset along the normal, relative to the scene size (metres)."""
        return 1e-5 * self.scale

