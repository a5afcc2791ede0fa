"""The state locator: which state point a surface hit lands on (thesis 3.1.2).

:class:`StateLocator` maps hits to the nearest state point on the same object and side;
:func:`buried_points` finds the states that no ray can reach (inside solids, pressed against
other objects). The passive dynamics and the bake's guide both use them.
"""
import numpy as np
from scipy.spatial import cKDTree

from .hemisphere import stratum_centers


class StateLocator:
    """Maps surface hits to the nearest state point on the same object and side (cKDTree).

    Distances are measured in 6D, ``(position, spacing·normal)`` with ``spacing`` the object's mean point
    spacing, so a hit prefers points on its own side and facet (thin walls, box edges); a match
    whose normal faces away from the hit side is rejected (-> void).

    Querying a tree for every ray would cost more than tracing it, so the nearest point is
    tabulated per triangle on a grid over its barycentric square, spanned by the two edges at the
    corner opposite the longest edge, whose cells are at most 1/``CELLS_PER_SPACING`` of the
    point spacing along each of those edges: a front-face hit takes the
    nearest point of its cell's centre. This resolves the nearest point to a quarter of the
    spacing (a hit may go to a neighbour that is at most one cell diagonal farther than the
    nearest; ``tests/engine/test_locator.py`` bounds how often). The cells of large
    triangles are filled a block at a time (:meth:`_fill_blocks`), with the same result as a
    query per cell centre. ``exact=True`` queries the trees for every hit instead. Back-face
    hits go to the void (:class:`~lmdp_addon.model.hits.HitClassifier`).
    """

    CELLS_PER_SPACING = 4
    MAX_CELLS = 4096
    #: Cells per block side and candidate points per block of :meth:`_fill_blocks`.
    BLOCK = 4
    BLOCK_CANDIDATES = 8

    def __init__(self, scene, states, exact=False):
        self.trees = {}
        self.spacing = np.zeros(len(scene.object_names))
        self.index = {}
        self.targets = None   #: bool mask of the points hits may land on (None: all; :meth:`exclude`)
        for o in np.unique(states.point_object):  # loop over objects, not rays
            ids = np.flatnonzero(states.point_object == o)
            area = float(states.point_area[ids].sum())
            spacing = np.sqrt(area / len(ids)) if area > 0 else 1.0
            feats = np.hstack([states.points[ids], spacing * states.normals[ids]])
            self.trees[int(o)] = cKDTree(feats)
            self.spacing[o] = spacing
            self.index[int(o)] = ids
        self.normals = states.normals
        self.scene = scene
        self.exact = bool(exact)
        self.face_normals = scene.triangle_geometry()[0]
        if not self.exact:
            self._build_grids(scene)

    def exclude(self, points, states):
        """Stop handing hits to ``points`` (bool mask over all points): they leave the trees,
        and the grid cells whose nearest point was one of them take their nearest remaining one."""
        points = np.asarray(points, dtype=bool)
        if not points.any():
            return
        self.targets = ~points if self.targets is None else self.targets & ~points
        for o in list(self.trees):
            ids = self.index[o]
            keep = ids[~points[ids]]
            if len(keep) == len(ids):
                continue
            if len(keep) == 0:
                del self.trees[o], self.index[o]
                continue
            self.trees[o] = cKDTree(np.hstack([states.points[keep], self.spacing[o] * states.normals[keep]]))
            self.index[o] = keep
        if self.exact or len(self.grid_point) == 0:
            return
        cells = np.flatnonzero((self.grid_point >= 0) & points[np.maximum(self.grid_point, 0)])
        if len(cells):
            t = np.searchsorted(self.grid_offset, cells, side="right") - 1
            rest = cells - self.grid_offset[t]
            self.grid_point[cells] = self.locate(self.cell_centres(t, rest // self.gv[t], rest % self.gv[t]),
                                                 self.face_normals[t], self.scene.triangle_object[t])

    def _build_grids(self, scene):
        has_tree = np.zeros(len(scene.object_names), dtype=bool)
        has_tree[list(self.trees)] = True
        tri_ok = scene.state_triangles() & has_tree[scene.triangle_object]
        spacing = np.maximum(self.spacing[scene.triangle_object], 1e-12)
        # Each grid spans its triangle from the corner opposite the longest edge: the two
        # shortest edges give the fewest cells (a right triangle's grid is then half full).
        c = scene.corners()
        edge = np.linalg.norm(c[:, [2, 0, 1]] - c[:, [1, 2, 0]], axis=2)   # opposite corners 0, 1, 2
        self.grid_origin = np.argmax(edge, axis=1).astype(np.int8)
        order = (self.grid_origin[:, None] + np.arange(3)) % 3
        self.grid_corners = np.take_along_axis(c, order[:, :, None], axis=1)
        e1, e2 = self.grid_edges()
        cells = self.CELLS_PER_SPACING / spacing
        gu = np.where(tri_ok, np.clip(np.ceil(cells * np.linalg.norm(e1, axis=1)), 1, self.MAX_CELLS), 0)
        gv = np.where(tri_ok, np.clip(np.ceil(cells * np.linalg.norm(e2, axis=1)), 1, self.MAX_CELLS), 0)
        self.gu = gu.astype(np.int64)
        self.gv = gv.astype(np.int64)
        self.grid_offset = np.concatenate([[0], np.cumsum(self.gu * self.gv)])[:-1]
        self.grid_point = np.full(int((self.gu * self.gv).sum()), -1, dtype=np.int32)
        if len(self.grid_point) == 0:
            return
        big = (self.gu >= self.BLOCK) & (self.gv >= self.BLOCK)
        self.cells_queried_exactly = 0
        small = np.flatnonzero((self.gu > 0) & ~big)
        if len(small):
            t, i, j = self._cells(small)
            self.grid_point[self.grid_offset[t] + i * self.gv[t] + j] = self.locate(
                self.cell_centres(t, i, j), self.face_normals[t], scene.triangle_object[t])
            self.cells_queried_exactly += len(t)
        if np.any(big):
            self._fill_blocks(scene, np.flatnonzero(big))

    def grid_edges(self):
        """The edges ``e1, e2 (T, 3)`` that span each triangle's grid from its origin corner."""
        g = self.grid_corners
        return g[:, 1] - g[:, 0], g[:, 2] - g[:, 0]

    def cell_centres(self, t, i, j):
        """World position of the centre of cell ``(i, j)`` of triangle ``t``'s grid."""
        e1, e2 = self.grid_edges()
        u = (i + 0.5) / self.gu[t]
        v = (j + 0.5) / self.gv[t]
        return self.grid_corners[t, 0] + u[:, None] * e1[t] + v[:, None] * e2[t]

    def cell_of(self, tri, u, v):
        """Index into the tables (``grid_point``) of the cell holding the point with ray-hit
        barycentrics ``(u, v)`` (weights of the triangle's second and third corner) on ``tri``."""
        r = np.take(self.grid_origin, tri)
        r0, r1 = r == 0, r == 1
        w0 = 1.0 - u - v
        gu_coord = np.where(r0, u, np.where(r1, v, w0))     # weight of corner r + 1
        gv_coord = np.where(r0, v, np.where(r1, w0, u))     # weight of corner r + 2
        gu = np.take(self.gu, tri)
        gv = np.take(self.gv, tri)
        i = np.multiply(gu_coord, gu).astype(np.int64)      # (float64 products, as numpy promotes)
        np.clip(i, 0, gu - 1, out=i)
        j = np.multiply(gv_coord, gv).astype(np.int64)
        np.clip(j, 0, gv - 1, out=j)
        i *= gv
        i += j
        i += np.take(self.grid_offset, tri)
        return i

    def _row_length(self, t, i):
        """Cells of row i of triangle t's grid that meet the triangle: ``j < gv (1 - i/gu)``."""
        n = np.ceil(self.gv[t] * (1.0 - i / self.gu[t]) - 1e-9).astype(np.int64)
        return np.clip(n, 1, self.gv[t])

    def _cells(self, tris):
        """(t, i, j) of every cell of the grids of ``tris`` that meets its triangle (vectorised
        over all rows of all triangles)."""
        gu = self.gu[tris]
        row_t = np.repeat(tris, gu)
        row_i = np.arange(len(row_t)) - np.repeat(np.cumsum(gu) - gu, gu)
        row_len = self._row_length(row_t, row_i)
        t = np.repeat(row_t, row_len)
        i = np.repeat(row_i, row_len)
        j = np.arange(len(t)) - np.repeat(np.cumsum(row_len) - row_len, row_len)
        return t, i, j

    def _fill_blocks(self, scene, tris):
        """Exact nearest compatible point of the centre of every cell of the grids of ``tris``.

        One tree query per block of ``BLOCK x BLOCK`` cells instead of one per cell: the
        ``BLOCK_CANDIDATES`` nearest points of the block's centre c are the candidates of its
        cells, and a cell centre x takes the nearest candidate, at distance d. Any point p
        nearer to x lies within ``d + |x - c|`` of c, so where that is below the distance of
        the last candidate the answer is exact; the few other cells query the tree themselves.
        Distances are 6-D as in :meth:`locate`; within a triangle the normal part is the same
        for x and c, so ``|p - x|² = |p - c|² - 2 (p - c)·(x - c) + |x - c|²``.
        """
        B = self.BLOCK
        gu, gv = self.gu, self.gv
        c = self.grid_corners
        e1, e2 = self.grid_edges()
        bt, i0, j0, i, j, valid = self._blocks(tris)
        cu = (i0 + np.minimum(i0 + B, gu[bt])) / (2.0 * gu[bt])     # the block's centre (u, v)
        cv = (j0 + np.minimum(j0 + B, gv[bt])) / (2.0 * gv[bt])
        du = (i + 0.5) / gu[bt, None] - cu[:, None]                 # x - c = du e1 + dv e2
        dv = (j + 0.5) / gv[bt, None] - cv[:, None]
        e11 = np.einsum("ij,ij->i", e1[bt], e1[bt])[:, None]
        e12 = np.einsum("ij,ij->i", e1[bt], e2[bt])[:, None]
        e22 = np.einsum("ij,ij->i", e2[bt], e2[bt])[:, None]
        dx = np.sqrt(np.maximum(du * du * e11 + 2.0 * du * dv * e12 + dv * dv * e22, 0.0))
        centre = c[bt, 0] + cu[:, None] * e1[bt] + cv[:, None] * e2[bt]
        found = np.full(i.shape, -1, dtype=np.int64)
        sure = np.zeros(i.shape, dtype=bool)
        objects = scene.triangle_object
        for o, tree in self.trees.items():  # loop over objects, not cells
            ob = np.flatnonzero(objects[bt] == o)
            if len(ob) == 0:
                continue
            found[ob], sure[ob] = self._nearest_candidates(o, tree, bt[ob], centre[ob], du[ob], dv[ob], dx[ob])
        redo = valid & ~sure
        if np.any(redo):
            rt = bt[np.nonzero(redo)[0]]
            found[redo] = self.locate(self.cell_centres(rt, i[redo], j[redo]), self.face_normals[rt], objects[rt])
            self.cells_queried_exactly += int(np.count_nonzero(redo))
        bt_cells = np.broadcast_to(bt[:, None], i.shape)[valid]
        self.grid_point[self.grid_offset[bt_cells] + i[valid] * gv[bt_cells] + j[valid]] = found[valid]

    def _blocks(self, tris):
        """The ``BLOCK x BLOCK`` blocks of cells that meet the triangles ``tris``: each block's
        triangle ``bt`` and first cell ``(i0, j0)``, and its cells ``(i, j) (blocks, BLOCK²)``
        with the mask ``valid`` of those that meet the triangle."""
        B, gu = self.BLOCK, self.gu
        # Blocks that meet the triangle: in block row I, those whose first cell is in row I*B.
        brows = -(-gu[tris] // B)
        row_t = np.repeat(tris, brows)
        row_I = np.arange(len(row_t)) - np.repeat(np.cumsum(brows) - brows, brows)
        per_row = -(-self._row_length(row_t, row_I * B) // B)
        bt = np.repeat(row_t, per_row)
        i0 = np.repeat(row_I, per_row) * B
        j0 = (np.arange(len(bt)) - np.repeat(np.cumsum(per_row) - per_row, per_row)) * B
        a = np.arange(B * B)
        i = i0[:, None] + a // B                              # (blocks, B*B) cells
        j = j0[:, None] + a % B
        valid = i < gu[bt, None]
        valid &= j < self._row_length(np.broadcast_to(bt[:, None], i.shape), np.minimum(i, gu[bt, None] - 1))
        return bt, i0, j0, i, j, valid

    def _nearest_candidates(self, o, tree, bt, centre, du, dv, dx):
        """For blocks of object ``o`` (triangles ``bt``, centres ``centre``; cell offsets ``du,
        dv`` and distances ``dx`` from the centre): the nearest candidate point of every cell,
        -1 where it faces away, and whether that answer is certain (:meth:`_fill_blocks`)."""
        k = min(self.BLOCK_CANDIDATES, tree.n)
        e1, e2 = self.grid_edges()
        q = np.hstack([centre, self.spacing[o] * self.face_normals[bt]])
        dist, near = tree.query(q, k=k, workers=-1)
        dist, near = dist.reshape(len(bt), 1, k), near.reshape(len(bt), 1, k)
        rel = tree.data[near[:, 0]][..., :3] - centre[:, None, :]      # p - c
        g1 = -2.0 * np.einsum("bkj,bj->bk", rel, e1[bt])[:, None, :]
        g2 = -2.0 * np.einsum("bkj,bj->bk", rel, e2[bt])[:, None, :]
        score = dist ** 2 + du[:, :, None] * g1 + dv[:, :, None] * g2   # |p - x|² - |x - c|²
        best = np.argmin(score, axis=2)[..., None]
        d_best = np.sqrt(np.maximum(np.take_along_axis(score, best, axis=2)[..., 0] + dx ** 2, 0.0))
        sure = (k == tree.n) | (d_best + dx < dist[:, :, -1] * (1.0 - 1e-9))
        ids = self.index[o][np.take_along_axis(near, best, axis=2)[..., 0]]
        facing = np.einsum("bcj,bj->bc", self.normals[ids], self.face_normals[bt]) > 0.0
        return np.where(facing, ids, -1), sure

    def locate_front(self, tri, u, v, positions=None, workers=-1):
        """Nearest compatible point for front-face hits on ``tri`` with barycentrics ``(u, v)``."""
        if self.exact:
            return self.locate(positions, self.face_normals[tri], self.scene.triangle_object[tri],
                               workers=workers)
        return np.take(self.grid_point, self.cell_of(tri, u, v)).astype(np.int64)

    def locate(self, positions, side_normals, objects, workers=-1):
        """Exact nearest point for each hit (tree query), -1 where the object has no states or
        the nearest point faces away from the hit side."""
        out = np.full(len(positions), -1, dtype=np.int64)
        for o, tree in self.trees.items():
            sel = np.flatnonzero(objects == o)
            if len(sel) == 0:
                continue
            q = np.hstack([positions[sel], self.spacing[o] * side_normals[sel]])
            _, nearest = tree.query(q, k=1, workers=workers)
            ids = self.index[o][nearest]
            facing = np.einsum("ij,ij->i", self.normals[ids], side_normals[sel]) > 0.0
            out[sel] = np.where(facing, ids, -1)
        return out


#: Probe directions of :func:`buried_points`: the centres of a 2 x 4 grid of strata.
BURIED_PROBES = (2, 4)
#: Probes that must meet a back face for a point to count as buried.
BURIED_BACK_HITS = 7


def buried_points(caster, states, lifted):
    """(m,) bool: hidden points, whose probe rays nearly all meet the back of a face.

    Such a point lies inside a closed solid, in a face pressed against another object (the floor
    under a box standing on it, the end of a slab that a wall covers) or right above the back of
    a light (the ceiling over a mesh light hanging 5 mm below it). A nearest-point lookup knows
    nothing of visibility: it would hand such a point the rays that land beside it, and with
    them whatever light is trapped there (no light at all inside a wall, the lamp's glow in the
    5 mm gap). So no ray lands on a buried point and its own rays go to the void: the states do
    not model light confined to spaces thinner than their spacing (the path tracer still does).
    Eight probe directions spread over the hemisphere (the centres of a 2 x 4 grid of strata);
    a point is buried when at least ``BURIED_BACK_HITS`` of them meet a back face, or a front
    face at a buried point (a face pressed against another solid is seen from inside that solid
    as a front face; one pass of this second rule, over the points the first rule nearly
    buried). A point that sees a few front faces or the sky is not buried.
    """
    local = stratum_centers(*BURIED_PROBES).astype(np.float32)       # (8, 3)
    n = len(local)
    m = len(lifted)
    dirs = np.matmul(local[None, :, :], states.frames.astype(np.float32)).reshape(-1, 3)
    origins = np.repeat(lifted, n, axis=0)
    tri, dist = caster.intersect(origins, dirs)
    scene = caster.scene
    normals = scene.triangle_geometry()[0]
    t = np.maximum(tri, 0)
    back = (tri >= 0) & (np.einsum("ij,ij->i", np.take(normals, t, axis=0), dirs) > 0)
    count = back.reshape(m, n).sum(axis=1)
    buried = count >= BURIED_BACK_HITS
    near = np.flatnonzero(~buried & (count >= BURIED_BACK_HITS - 3))
    if len(near) and buried.any():
        rays = (near[:, None] * n + np.arange(n)).ravel()
        rays = rays[(tri[rays] >= 0) & ~back[rays]
                    & scene.object_carries_states[scene.triangle_object[t[rays]]]]
        hits = origins[rays].astype(np.float64) + dirs[rays] * dist[rays, None]
        onto = np.zeros(len(rays), dtype=bool)
        for o in np.unique(scene.triangle_object[t[rays]]):   # loop over objects, not rays
            sel = np.flatnonzero(scene.triangle_object[t[rays]] == o)
            ids = np.flatnonzero(states.point_object == o)
            if len(ids) == 0:
                continue
            _, k = cKDTree(states.points[ids]).query(hits[sel], k=1)
            onto[sel] = buried[ids[k]] & (np.einsum("ij,ij->i", states.normals[ids[k]], normals[t[rays[sel]]]) > 0)
        extra = np.bincount(rays[onto] // n, minlength=m)
        buried |= count + extra >= BURIED_BACK_HITS
    return buried
