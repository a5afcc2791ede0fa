"""Light connections: light vertices traced from the emitters and joined to the eye paths' vertices.

A path y_0 (the texel point) ... y_k of the tracer finds the light that surfaces reflect only by
its own directions. With ``light_share`` s > 0 each path also gets, with probability s, a short
light path: a point l on the emitter triangles (probability ∝ area x radiance, uniform on the
triangle: density ``P_l`` per unit area), a side of a two-sided emitter with probability 1/2
(``p_side``), a cosine direction from it and that ray's first hit y'_1, then a cosine direction
from y'_1 and its first hit y'_2 (:class:`LightVertices`). Every Lambertian eye vertex y_k within
the bounce limits is joined to y'_1 (a path y_k → y'_1 → l) and to y'_2 (y_k → y'_2 → y'_1 → l)
by shadow rays (:func:`connect`). The light vertices land ∝ the light they receive, to the
millimetre: the ceiling beside a lamp hung close to it, or the patch of a room the light reaches
through a hatch after one bounce, get their share without any table.

**Balance heuristic** (Veach 1997, ch. 10). A path that ends ... y_{m-2} → y_{m-1} → y_m → l
(y_m Lambertian) is found by four strategies, with densities per unit area of its vertices
(the factor ``cos θ_l / r²`` of l, common to all, cancelled, and divided by the eye density
``pe_{m-1}`` of y_{m-1}):

    A = pe_m p_L               the eye path to y_m and the light sample at y_m
    B = pe_m q                 the eye path to y_m and its BSDF ray hitting l (q = cos θ / π)
    C = s P_l p_side q_g       the eye path to y_{m-1} joined to y'_1 = y_m
    E = s P_l p_side q_g pl_m / pe_{m-1}   the eye path to y_{m-2} joined to y'_2 = y_{m-1}

with pe_m the density of y_m from y_{m-1} (the direction density there x cos θ_m / r²), p_L the
light-sampling density of l at y_m per steradian, q_g the geometric cosine at y_m towards l over
π, pl_m the light path's density of y_{m-1} from y_m (cos θ_m / π x cos θ_{m-1} / r²). C and E
count only where the vertex they join was eligible and the light vertices are connectable
(Lambertian, not emitting). Each strategy's sample is weighted by its term over their sum: the
weights sum to 1 for every path, whatever s, so the bake is unbiased. The tracer's light sample
and emitter hit keep their old weights times ``(A + B) / (A + B + C + E)`` (:meth:`JoinState.hook`).
"""
import numpy as np

from ..sampling import cosine_directions, dot, rows, spherical_triangle_solid_angle, table_index

INV_PI = 1.0 / np.pi


def _ratio(shading, geometric):
    """Shading over geometric cosine (1 on flat triangles), 0 where the geometric one is 0."""
    return np.where(geometric > 0, shading / np.where(geometric > 0, geometric, 1.0), 0.0)


class LightVertices:
    """The light vertices of one wavefront (``sample``): per path at most one y'_1 and one y'_2,
    with what their connections need."""

    def __init__(self, tracer, n, rng, stats):
        self.tracer = tracer
        self.n = n
        self.first = self.second = None
        self._sample(tracer, n, rng, stats)

    def _sample(self, tr, n, rng, stats):
        E, s = tr.lights, tr.light_share
        u = rng.random((n, 4))
        take = np.flatnonzero(u[:, 3] < s)
        if len(take) == 0:
            return
        u = u[take]
        e = table_index(E.power_cdf32, u[:, 0].astype(np.float32))
        sq = np.sqrt(u[:, 1])
        b = sq * u[:, 2]
        a = sq - b
        lpos = E.v0[e] + a[:, None] * E.e1[e] + b[:, None] * E.e2[e]
        n_l = E.normals[e].copy()
        two = E.two_sided[e]
        n_l[two & (rng.random(len(take)) < 0.5)] *= -1
        p_side = np.where(two, 0.5, 1.0)
        d = cosine_directions(n_l.astype(np.float32), rng.random((len(take), 2)), stratified=False)
        origin = (lpos + tr.caster.offset(E.triangles[e])[:, None] * n_l).astype(np.float32)
        hit1 = _hits(tr, origin, d, stats)
        if hit1 is None:
            return
        k, t, bu, bv, dist = hit1
        path, e, d, p_side, n_l = take[k], e[k], d[k], p_side[k], n_l[k]
        y, ng, ns = _vertex(tr, t, bu, bv, d)
        # the light sample's and the emitter hit's densities of l at y'_1 (as the tracer's)
        q = np.maximum(dot(ns, -d), 0.0).astype(np.float64) * INV_PI
        cos_g = dot(ng, -d).astype(np.float64)
        r = dist.astype(np.float64)
        cos_l = np.abs(dot(n_l.astype(np.float32), d)).astype(np.float64)
        p_light = E.pdf_area32[e].astype(np.float64) * r * r / np.maximum(cos_l, 1e-12)
        yo = (y + np.take(tr.offsets, t)[:, None] * ng).astype(np.float32)
        near = np.flatnonzero(E.near(tuple(np.ascontiguousarray(yo[:, i]) for i in range(3)), e))
        if len(near):
            omega = spherical_triangle_solid_angle(E.corners64[e[near]] - yo[near, None, :].astype(np.float64))
            p_light[near] = E.power_prob[e[near]] / np.maximum(omega, 1e-300)
        albedo = _albedo(tr, t, bu, bv)
        base = ((_ratio(q * np.pi, cos_g) / (s * np.pi * E.pdf_area32[e] * p_side))[:, None]
                * albedo * E.radiance32[e])
        slot = np.full(n, -1, np.int64)
        slot[path] = np.arange(len(path))
        self.first = dict(slot=slot, y=y, ng=ng, ns=ns, tri=t, p_light=p_light, q=q,
                          s_lt=s * E.pdf_area32[e] * p_side * cos_g * INV_PI, base=base.astype(np.float32))
        # ---- y'_2: a cosine bounce at y'_1 ----
        d2 = cosine_directions(ns.astype(np.float32), rng.random((len(path), 2)), stratified=False)
        up = dot(ng, d2) > 0
        o2 = (y + np.take(tr.offsets, t)[:, None] * ng).astype(np.float32)
        keep = np.flatnonzero(up)
        hit2 = _hits(tr, o2[keep], d2[keep], stats) if len(keep) else None
        if hit2 is None:
            return
        k2, t2, bu2, bv2, dist2 = hit2
        j = keep[k2]                      # rows of self.first
        d2 = d2[j]
        y2, ng2, ns2 = _vertex(tr, t2, bu2, bv2, d2)
        r2 = dist2.astype(np.float64)
        cos_g1_out = dot(rows(ng, j), d2).astype(np.float64)
        cos_s1_out = dot(rows(ns, j), d2).astype(np.float64)
        cos_g2 = dot(ng2, -d2).astype(np.float64)
        cos_s2 = np.maximum(dot(ns2, -d2), 0.0).astype(np.float64)
        states2 = np.full(len(j), -1, np.int64)
        if tr.guide is not None:
            front = dot(rows(tr.face_normals, t2), d2) < 0
            states2 = tr.guide.states_at_hits(t2, bu2, bv2, y2, ng2, front, np.take(tr.objects, t2))
        # the eye path's density of y'_1 from y'_2 and the light path's of y'_2 from y'_1
        pe12 = tr.directions.density(ns2, states2, -d2, False) * cos_g1_out / (r2 * r2)
        pl12 = np.maximum(cos_s1_out, 0.0) * INV_PI * cos_g2 / (r2 * r2)
        base2 = rows(base, j) * (_albedo(tr, t2, bu2, bv2)
                                 * (_ratio(cos_s2, cos_g2) * _ratio(cos_g1_out, cos_s1_out))[:, None])
        slot2 = np.full(n, -1, np.int64)
        slot2[path[j]] = np.arange(len(j))
        self.second = dict(slot=slot2, y=y2, ng=ng2, tri=t2, first=j, pe12=pe12, pl12=pl12,
                           base=base2.astype(np.float32))


def _hits(tr, origin, d, stats):
    """``(rows, tri, bu, bv, dist)`` of the rays that hit a connectable triangle, or None."""
    tri, dist, bu, bv = tr.caster.intersect(origin, d, barycentrics=True)
    stats.rays += len(origin)
    k = np.flatnonzero((tri >= 0) & tr.connectable[np.maximum(tri, 0)])
    stats.light_vertices += len(k)
    if len(k) == 0:
        return None
    return k, tri[k], bu[k], bv[k], dist[k]


def _vertex(tr, t, bu, bv, d):
    """Position, geometric and shading normal (of the side the ray ``d`` arrived on) of hits."""
    y = rows(tr.corner0, t) + rows(tr.edge1, t) * bu[:, None] + rows(tr.edge2, t) * bv[:, None]
    ng = rows(tr.face_normals, t)
    front = dot(ng, d) < 0
    np.negative(ng, out=ng, where=~front[:, None])
    ns = tr.scene.shading_normals(t, bu, bv, side=front) if tr.smooth else ng
    return y, ng, ns


def _albedo(tr, t, bu, bv):
    return tr.scene.albedo_at(t, bu, bv) if tr.textured else rows(tr.albedo, t)


class JoinState:
    """Per path: what the balance heuristic needs of its last three eye vertices (module
    docstring): pe of the current and the previous vertex, whether the previous ones were joined
    (eligible for y'_1 / y'_2 connections), whether the current and the previous are
    connectable, and the geometry back to the previous vertex (for pl)."""

    def __init__(self, n, share, lights):
        self.share = share
        self.lights = lights
        self.pe = np.full(n, np.inf)          # density of y_k from y_{k-1}
        self.pe_prev = np.full(n, np.inf)     # density of y_{k-1} from y_{k-2}
        self.join1 = np.zeros(n, bool)        # y_k eligible for a y'_1 connection (set at y_k)
        self.join2 = np.zeros(n, bool)        # y_k eligible for a y'_2 connection
        self.join1_prev = np.zeros(n, bool)
        self.join2_prev = np.zeros(n, bool)
        self.join2_prev2 = np.zeros(n, bool)
        self.conn = np.zeros(n, bool)         # y_k connectable
        self.conn_prev = np.zeros(n, bool)
        self.back = np.zeros((n, 3), np.float32)   # the direction that arrived at y_k
        self.back_geo = np.zeros(n)           # cos θ_{k-1} / r² of that ray at y_{k-1}

    def _terms(self, p, p_light, q, s_lt, pl):
        """(A + B) / (A + B + C + E) for paths ``p`` (module docstring)."""
        a = np.take(self.pe, p) * (p_light + q)
        c = np.where(np.take(self.join1_prev, p) & np.take(self.conn, p), s_lt, 0.0)
        e2 = (np.take(self.join2_prev2, p) & np.take(self.conn_prev, p) & np.take(self.conn, p))
        pe_prev = np.take(self.pe_prev, p)
        e = np.where(e2 & np.isfinite(pe_prev) & (pe_prev > 0),
                     s_lt * pl / np.where(np.isfinite(pe_prev) & (pe_prev > 0), pe_prev, 1.0), 0.0)
        den = a + c + e
        ok = np.isfinite(a) & (den > 0) & ((c > 0) | (e > 0))
        return np.where(ok, a / np.where(ok, den, 1.0), 1.0)

    def _s_lt(self, ev, q_g):
        E = self.lights
        return self.share * E.pdf_area32[ev] * np.where(E.two_sided[ev], 0.5, 1.0) * np.maximum(q_g, 0.0)

    def hook(self, idx, nrm):
        """``mis_hook`` of the light samples at the current vertices of the paths ``idx``
        (shading normals ``nrm``): the factor ``(A + B) / (A + B + C + E)`` of each sample."""
        pl = (np.maximum(dot(nrm, -rows(self.back, idx)), 0.0).astype(np.float64) * INV_PI
              * np.take(self.back_geo, idx))

        def share(vis, ev, p_light, q, q_g):
            p = np.take(idx, vis)
            return self._terms(p, p_light, q, self._s_lt(ev, q_g), np.take(pl, vis)).astype(np.float32)
        return share

    def emission_hook(self, idx, nrm, gnrm, d):
        """``mis_hook`` of the emitter hits of the rays ``d`` just traced from the current
        vertices (shading / geometric normals ``nrm`` / ``gnrm``): the same factor, taken before
        :meth:`arrive` moves the state on."""
        if not np.any(np.take(self.join1_prev, idx) | np.take(self.join2_prev2, idx)):
            return None
        q_g = np.maximum(dot(gnrm, d), 0.0).astype(np.float64) * INV_PI
        pl = (np.maximum(dot(nrm, -rows(self.back, idx)), 0.0).astype(np.float64) * INV_PI
              * np.take(self.back_geo, idx))
        snapshot = {name: np.take(getattr(self, name), idx) for name in
                    ("pe", "pe_prev", "join1_prev", "join2_prev2", "conn", "conn_prev")}
        rowstate = _Rows(snapshot, self.share, self.lights)

        def share(ray, ev, p_light, q):
            return rowstate._terms(ray, p_light, q, rowstate._s_lt(ev, np.take(q_g, ray)), np.take(pl, ray))
        return share

    def arrive(self, tr, idx, h, d, w, cos_prev, tri, dist, gnrm_from):
        """The rays ``d`` of the paths ``idx`` (drawn with weights ``w``, cosines ``cos_prev``
        at vertices with geometric normals ``gnrm_from``) hit ``tri`` at ``dist`` (rows ``h``):
        the state moves on by one vertex."""
        self.pe_prev[idx] = np.take(self.pe, idx)
        self.join2_prev2[idx] = np.take(self.join2_prev, idx)
        self.join1_prev[idx] = np.take(self.join1, idx)
        self.join2_prev[idx] = np.take(self.join2, idx)
        self.conn_prev[idx] = np.take(self.conn, idx)
        self.join1[idx] = False
        self.join2[idx] = False
        self.pe[idx] = np.inf
        self.conn[idx] = False
        t = np.take(tri, h)
        p = np.take(idx, h)
        wk = np.take(w, h).astype(np.float64)
        r = np.take(dist, h).astype(np.float64)
        dh = rows(d, h)
        cos_h = np.abs(dot(rows(tr.face_normals, t), dh)).astype(np.float64)
        p_dir = np.maximum(np.take(cos_prev, h), 0.0) * INV_PI / np.where(wk > 0, wk, 1.0)
        good = (wk > 0) & (r > 0)
        r2 = np.where(good, r * r, 1.0)
        self.pe[p] = np.where(good, p_dir * cos_h / r2, np.inf)
        self.conn[p] = tr.connectable[t] & good
        self.back[p] = dh
        self.back_geo[p] = np.where(good, np.maximum(dot(rows(gnrm_from, h), dh), 0.0) / r2, 0.0)


class _Rows(JoinState):
    """A :class:`JoinState` restricted to some rows (the emitter hits' snapshot)."""

    def __init__(self, arrays, share, lights):
        self.share = share
        self.lights = lights
        for name, value in arrays.items():
            setattr(self, name, value)


def connect(tr, L, lv, js, idx, pos, nrm, gnrm, lift, beta, states, first, bounce, eligible2, stats):
    """Joins the eye vertices ``pos`` of the paths ``idx`` (throughput ``beta``, None: 1; the
    guide's ``states``; ``first``: the texel points) to their light vertices: y'_1 always, y'_2
    where ``eligible2``; adds the light of vertices ``bounce + 1`` and ``bounce + 2`` with the
    balance heuristic (module docstring)."""
    if lv.first is not None:
        _connect(tr, L, lv, js, lv.first, idx, pos, nrm, gnrm, lift, beta, states, first, bounce + 1, None, stats)
    if lv.second is not None:
        e = np.flatnonzero(eligible2)
        if len(e):
            _connect(tr, L, lv, js, lv.second, idx[e], rows(pos, e), rows(nrm, e), rows(gnrm, e), np.take(lift, e),
                     None if beta is None else rows(beta, e), np.take(states, e), first, bounce + 2, lv.first, stats)


def _connect(tr, L, lv, js, vertex, idx, pos, nrm, gnrm, lift, beta, states, first, bounce, first_vertices, stats):
    j = np.take(vertex["slot"], idx)
    has = np.flatnonzero(j >= 0)
    if len(has) == 0:
        return
    j = j[has]
    y = rows(vertex["y"], j)
    ox = rows(pos, has) + np.take(lift, has)[:, None] * rows(gnrm, has)
    to = y - ox
    r2 = dot(to, to).astype(np.float64)
    r = np.sqrt(r2)
    om = (to / np.where(r > 0, r, 1.0)[:, None].astype(np.float32)).astype(np.float32)
    cos_x = dot(rows(nrm, has), om)
    cos_xg = dot(rows(gnrm, has), om)
    cos_y = -dot(rows(vertex["ng"], j), om)
    ok = np.flatnonzero((cos_x > 0) & (cos_xg > 0) & (cos_y > 0) & (r > 0))
    if len(ok) == 0:
        return
    tmax = tr.caster.shadow_distance(r[ok], np.take(vertex["tri"], j[ok]))
    stats.shadow_rays += len(ok)
    vis = ok[~tr.caster.occluded(rows(ox, ok), rows(om, ok), tmax)]
    stats.connections += len(vis)
    if len(vis) == 0:
        return
    jv, hv = j[vis], has[vis]
    p_dir = tr.directions.density(rows(nrm, hv), np.take(states, hv), rows(om, vis), first)
    px = p_dir * cos_y[vis] / r2[vis]                 # this vertex's density of the light vertex
    f1 = lv.first
    if first_vertices is None:       # y'_1: C over A + B + C + E
        s_lt = np.take(f1["s_lt"], jv)
        a = px * (np.take(f1["p_light"], jv) + np.take(f1["q"], jv))
        p = np.take(idx, hv)
        # E: the eye path's previous vertex joined to this vertex as y'_2
        pl = (np.maximum(dot(rows(f1["ns"], jv), -rows(om, vis)), 0.0).astype(np.float64) * INV_PI
              * cos_xg[vis] / r2[vis])
        pe = np.take(js.pe, p)
        e2 = np.take(js.join2_prev, p) & np.take(js.conn, p) & np.isfinite(pe) & (pe > 0)
        e = np.where(e2, s_lt * pl / np.where(e2, pe, 1.0), 0.0)
        den = a + s_lt + e
        weight = np.where(den > 0, s_lt / np.where(den > 0, den, 1.0), 0.0)
    else:                            # y'_2: E over A + B + C + E
        i1 = np.take(vertex["first"], jv)
        s_lt = np.take(f1["s_lt"], i1)
        e = s_lt * np.take(vertex["pl12"], jv)
        den = px * (np.take(vertex["pe12"], jv) * (np.take(f1["p_light"], i1) + np.take(f1["q"], i1)) + s_lt) + e
        weight = np.where(den > 0, e / np.where(den > 0, den, 1.0), 0.0)
    g = cos_x[vis] * cos_y[vis] / r2[vis]
    value = (g * weight).astype(np.float32)[:, None] * rows(vertex["base"], jv)
    if beta is not None:
        value = value * rows(beta, hv)
    tr._add(L, idx[hv], value, bounce, None, stats)
