"""Ray casting with embreex (Embree 4): batched closest-hit and occlusion queries.

All queries take large numpy batches; the caller offsets the ray origin along the normal by
:meth:`RayCaster.offset` of the triangle it leaves, to avoid self-intersection.

**Ray offsets.** A point on a surface is known to float32 precision (the tracer's arrays and
embree's), and embree intersects a triangle to within a few units in the last place (ulp) of its
corners' coordinates. So the offset that keeps a ray from finding its own surface again scales
with the magnitude of the coordinates where it starts, like Cycles' and pbrt's epsilons: it is
``RELATIVE_OFFSET`` (8 float32 ulps) times the largest coordinate magnitude of the triangle and
of the triangles that share a vertex with it (an edge-adjacent triangle reaching farther out is
intersected less precisely). Nothing far away changes the offsets in a room: a 100 km ground
plane only lifts the rays that leave the ground plane itself. Eight ulps are a factor 4 above
where rays start to find their own surface on the bumpy, finely subdivided walls of the HEAVY
scene, and small enough that a room far from the world origin keeps its thin gaps (at 1 km from
it, 1 mm; the Cornell box's light hangs 5 mm below the ceiling).
"""
import numpy as np

from .errors import SceneError
from .scene_arrays import MAX_COORDINATE

#: Rays per embreex call: large enough to amortise the call, small enough for memory.
BATCH = 1 << 20
#: Ray origin offset per unit of coordinate magnitude (metres per metre): 8 float32 ulps.
RELATIVE_OFFSET = 2.0 ** -20
#: Smallest offset (metres): geometry at the world origin still gets a lift above rounding.
MIN_OFFSET = 1e-9


class RayCaster:
    """Embree scene of all valid triangles of a :class:`~lmdp_addon.scene_arrays.SceneArrays`.

    ``intersect`` returns the hit triangle (index into the *scene's* triangles, -1 for a miss) and
    the hit distance. Degenerate triangles and those the scene leaves out (non-finite or huge
    corners, ``SceneArrays.usable_triangles``) are not in the BVH.

    triangle_offset  (T,) float64 ray origin offset of each scene triangle (metres; module
                     docstring), 0 for the triangles that are not in the BVH
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
        # triangles only use usable vertices (finite, within ±MAX_COORDINATE); the others are zeroed.
        with np.errstate(invalid="ignore"):
            usable = np.all(np.abs(scene.vertices) <= MAX_COORDINATE, axis=1)
        vertices = np.where(usable[:, None], scene.vertices, 0.0).astype(np.float32)
        self._embree = rtcore_scene.EmbreeScene()
        TriangleMesh(self._embree, vertices, np.ascontiguousarray(scene.triangles[valid], dtype=np.int32))
        self.triangle_offset = triangle_offsets(scene, valid)
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

    def offset(self, triangles=None):
        """Origin offset along the normal (metres) of rays leaving ``triangles (n,)`` (scene
        triangle indices): ``(n,) float64``. Without ``triangles`` the largest offset of any
        triangle, one number that keeps every ray clear of its surface (and lifts rays in a room
        by the scale of the farthest geometry; the engine always passes the triangles)."""
        if triangles is None:
            return float(self.triangle_offset.max())
        return np.take(self.triangle_offset, triangles)

    def lift(self, points, normals, triangles):
        """``points + offset(triangles) · normals``: ray origins off the surfaces (float64)."""
        return points + self.offset(triangles)[:, None] * normals

    def shadow_distance(self, distances, targets):
        """Length of shadow rays that end on the scene triangles ``targets (n,)`` at
        ``distances (n,)``: short of the target surface by its offset and by embree's
        precision along the ray (``RELATIVE_OFFSET`` of the length), at least 0."""
        d = np.asarray(distances, dtype=np.float64)
        return np.maximum(d * (1.0 - RELATIVE_OFFSET) - self.offset(targets), 0.0)


def triangle_offsets(scene, valid):
    """(T,) ray origin offsets of the triangles ``valid`` (indices; 0 for the others):
    ``RELATIVE_OFFSET`` x the largest |coordinate| of the triangle's corners and of the
    triangles sharing a vertex with it, at least ``MIN_OFFSET`` (module docstring)."""
    tris = scene.triangles[valid]
    magnitude = np.abs(scene.vertices).max(axis=1)[tris].max(axis=1)     # (k,) metres
    at_vertex = np.zeros(len(scene.vertices))
    for corner in range(3):                 # a loop over the three corners, not over triangles
        np.maximum.at(at_vertex, tris[:, corner], magnitude)
    offset = np.zeros(scene.n_triangles)
    offset[valid] = np.maximum(RELATIVE_OFFSET * at_vertex[tris].max(axis=1), MIN_OFFSET)
    return offset

