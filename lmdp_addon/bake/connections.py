"""Light connections: light vertices traced from the emitters and joined to the eye paths' vertices.

A path y_0 (the texel point) ... y_k of the tracer finds the light that surfaces reflect only by
its own directions. With ``light_share`` s > 0 each path also gets, with probability s, a light
vertex (:class:`LightVertices`): a point l on the emitter triangles (probability ∝ area x
radiance, uniform on the triangle: density ``P_l`` per unit area), a side of a two-sided emitter
with probability 1/2 (``p_side``), a cosine direction from it and that ray's first hit y' on a
connectable surface (Lambertian, not emitting). Every Lambertian eye vertex y_k within the bounce
limits is joined to y' by a shadow ray (:func:`connect`): the path y_k → y' → l. The light
vertices land ∝ the light they receive, to the millimetre: the ceiling beside a lamp hung close
to it gets its share without any table.

**Balance heuristic** (Veach 1997, ch. 9–10). A path ... y_{m-1} → y_m → l (y_m Lambertian) is
found by three strategies, with densities per unit area of its vertices (the factor
``cos θ_l / r²`` of l and the eye densities up to y_{m-1}, common to all, cancelled):

    A = pe_m p_L              the eye path to y_m and the light sample at y_m
    B = pe_m q                the eye path to y_m and its BSDF ray hitting l (q = cos θ / π)
    C = s P_l p_side q_g      the eye path to y_{m-1} joined to the light vertex y' = y_m

with pe_m the density of y_m from y_{m-1} (the direction density there x cos θ_m / r²), p_L the
light-sampling density of l at y_m per steradian and q_g the geometric cosine at y_m towards l
over π; C counts only where y_{m-1} was joined (eligible) and y_m is connectable. Each
strategy's sample is weighted by its term over A + B + C: the weights sum to 1 for every path,
whatever s, so the bake is unbiased. The tracer's light sample and emitter hit keep their
two-strategy weights times ``(A + B) / (A + B + C)`` (:meth:`JoinState.hook`,
:meth:`JoinState.emission_hook`); a connection adds

    β G(y_k, y') ρ(y') L_e (cos_s / cos_g)(y') / (π s P_l p_side) x C / (A + B + C),

G = cos θ_k cos θ' / r², cos_s / cos_g the shading over the geometric cosine of the light's
arrival at y' (its f / (s P_lt), f the path's contribution to the estimate).
"""
import numpy as np

from ..sampling import cosine_directions, dot, rows, table_index

INV_PI = 1.0 / np.pi


def _ratio(shading, geometric):
    """Shading over geometric cosine (1 on flat triangles), 0 where the geometric one is 0."""
    return np.where(geometric > 0, shading / np.where(geometric > 0, geometric, 1.0), 0.0)


class LightVertices:
    """The light vertices of one wavefront: per path at most one y' (``first``: its slot per
    path, position, normals, triangle, the densities of l at y' and the light it sends,
    ``base`` = ρ(y') L_e (cos_s / cos_g) / (π s P_l p_side))."""

    def __init__(self, tracer, n, rng, stats):
        self.first = None
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
        y, ns, ng, _, albedo = tr.hit_points(d, t, bu, bv)
        # the light sample's and the emitter hit's densities of l at y'_1 (as the tracer's)
        q = np.maximum(dot(ns, -d), 0.0).astype(np.float64) * INV_PI
        cos_g = dot(ng, -d).astype(np.float64)
        cos_l = np.maximum(np.abs(dot(n_l.astype(np.float32), d)).astype(np.float64), 1e-12)
        yo = (y + np.take(tr.offsets, t)[:, None] * ng).astype(np.float32)   # lifted as the light sample's
        p_light = E.light_density(yo, e, dist.astype(np.float64), cos_l)
        base = ((_ratio(q * np.pi, cos_g) / (s * np.pi * E.pdf_area32[e] * p_side))[:, None]
                * albedo * E.radiance32[e])
        slot = np.full(n, -1, np.int64)
        slot[path] = np.arange(len(path))
        self.first = dict(slot=slot, y=y, ng=ng, tri=t, p_light=p_light, q=q,
                          s_lt=s * E.pdf_area32[e] * p_side * cos_g * INV_PI, base=base.astype(np.float32))

    def extend(self, parents):
        """New paths (copies of a split, ``splitting``) that share the light vertices of ``parents``."""
        if self.first is not None:
            self.first["slot"] = np.concatenate([self.first["slot"], np.take(self.first["slot"], parents)])


def _hits(tr, origin, d, stats):
    """``(rows, tri, bu, bv, dist)`` of the rays that hit a connectable triangle, or None."""
    tri, dist, bu, bv = tr.caster.intersect(origin, d, barycentrics=True)
    stats.rays += len(origin)
    k = np.flatnonzero((tri >= 0) & tr.connectable[np.maximum(tri, 0)])
    stats.light_vertices += len(k)
    if len(k) == 0:
        return None
    return k, tri[k], bu[k], bv[k], dist[k]


class JoinState:
    """Per path: what the balance heuristic needs of its last eye vertices (module docstring):
    pe of the current vertex, whether the previous one was joined, whether the current one is
    connectable."""

    def __init__(self, n, share, lights):
        self.share = share
        self.lights = lights
        self.pe = np.full(n, np.inf)          # density of y_k from y_{k-1}
        self.joined = np.zeros(n, bool)       # y_k joined to its light vertex (set at y_k)
        self.joined_prev = np.zeros(n, bool)  # y_{k-1} was
        self.conn = np.zeros(n, bool)         # y_k connectable

    def extend(self, parents):
        """New paths (copies of a split, ``splitting``) in the state of ``parents``."""
        for name in ("pe", "joined", "joined_prev", "conn"):
            a = getattr(self, name)
            setattr(self, name, np.concatenate([a, np.take(a, parents)]))

    def _kept(self, pe, joined_prev, conn, p_light, q, s_lt):
        """(A + B) / (A + B + C) (module docstring; 1 where C does not count)."""
        c = np.where(joined_prev & conn, s_lt, 0.0)
        joined = (c > 0) & np.isfinite(pe)
        a = np.where(joined, pe, 0.0) * (p_light + q)
        den = a + c
        ok = joined & (den > 0)
        return np.where(ok, a / np.where(ok, den, 1.0), 1.0)

    def _s_lt(self, ev, q_g):
        E = self.lights
        return self.share * E.pdf_area32[ev] * np.where(E.two_sided[ev], 0.5, 1.0) * np.maximum(q_g, 0.0)

    def hook(self, idx):
        """``mis_hook`` of the light samples at the current vertices of the paths ``idx``."""
        def share(vis, ev, p_light, q, q_g):
            p = np.take(idx, vis)
            return self._kept(np.take(self.pe, p), np.take(self.joined_prev, p), np.take(self.conn, p), p_light, q,
                              self._s_lt(ev, q_g)).astype(np.float32)
        return share

    def emission_hook(self, idx, gnrm, d):
        """``mis_hook`` of the emitter hits of the rays ``d`` just traced from the current
        vertices (geometric normals ``gnrm``): the same factor, taken before :meth:`arrive`
        moves the state on; None when no vertex counts."""
        joined_prev, conn = np.take(self.joined_prev, idx), np.take(self.conn, idx)
        if not np.any(joined_prev & conn):
            return None
        pe = np.take(self.pe, idx)
        q_g = np.maximum(dot(gnrm, d), 0.0).astype(np.float64) * INV_PI

        def share(ray, ev, p_light, q):
            return self._kept(np.take(pe, ray), np.take(joined_prev, ray), np.take(conn, ray), p_light, q,
                              self._s_lt(ev, np.take(q_g, ray)))
        return share

    def arrive(self, tr, idx, h, d, w, cos_prev, tri, dist):
        """The rays ``d`` of the paths ``idx`` (drawn with weights ``w`` and cosines ``cos_prev``)
        hit ``tri`` at ``dist`` (rows ``h``): the state moves on by one vertex."""
        self.joined_prev[idx] = np.take(self.joined, idx)
        self.joined[idx] = False
        self.pe[idx] = np.inf
        self.conn[idx] = False
        t = np.take(tri, h)
        p = np.take(idx, h)
        wk = np.take(w, h).astype(np.float64)
        r = np.take(dist, h).astype(np.float64)
        cos_h = np.abs(dot(rows(tr.face_normals, t), rows(d, h))).astype(np.float64)
        p_dir = np.maximum(np.take(cos_prev, h), 0.0) * INV_PI / np.where(wk > 0, wk, 1.0)
        good = (wk > 0) & (r > 0)
        self.pe[p] = np.where(good, p_dir * cos_h / np.where(good, r * r, 1.0), np.inf)
        self.conn[p] = tr.connectable[t] & good


def connect(tr, L, lv, idx, pos, nrm, gnrm, lift, beta, states, first, bounce, stats):
    """Joins the eye vertices ``pos`` of the paths ``idx`` (shading / geometric normals ``nrm`` /
    ``gnrm``, ray offsets ``lift``, throughput ``beta``, None: 1; the guide's ``states``;
    ``first``: the texel points) to their light vertices by shadow rays and adds the light of the
    paths y → y' → l (a vertex ``bounce + 1``) with the balance-heuristic weight C / (A + B + C)."""
    f = lv.first
    if f is None:
        return
    j = np.take(f["slot"], idx)
    has = np.flatnonzero(j >= 0)
    if len(has) == 0:
        return
    j = j[has]
    ox = rows(pos, has) + np.take(lift, has)[:, None] * rows(gnrm, has)
    to = rows(f["y"], j) - ox
    r2 = dot(to, to).astype(np.float64)
    r = np.sqrt(r2)
    om = (to / np.where(r > 0, r, 1.0)[:, None].astype(np.float32)).astype(np.float32)
    cos_x = dot(rows(nrm, has), om)
    cos_y = -dot(rows(f["ng"], j), om)
    ok = np.flatnonzero((cos_x > 0) & (dot(rows(gnrm, has), om) > 0) & (cos_y > 0) & (r > 0))
    if len(ok) == 0:
        return
    tmax = tr.caster.shadow_distance(r[ok], np.take(f["tri"], j[ok]))
    stats.shadow_rays += len(ok)
    vis = ok[~tr.caster.occluded(rows(ox, ok), rows(om, ok), tmax)]
    stats.connections += len(vis)
    if len(vis) == 0:
        return
    jv, hv = j[vis], has[vis]
    p_dir = tr.directions.density(rows(nrm, hv), np.take(states, hv), rows(om, vis), first)
    px = p_dir * cos_y[vis] / r2[vis]                 # this vertex's density of y' per unit area
    s_lt = np.take(f["s_lt"], jv)
    den = px * (np.take(f["p_light"], jv) + np.take(f["q"], jv)) + s_lt
    weight = np.where(den > 0, s_lt / np.where(den > 0, den, 1.0), 0.0)
    g = cos_x[vis] * cos_y[vis] / r2[vis]
    value = (g * weight).astype(np.float32)[:, None] * rows(f["base"], jv)
    if beta is not None:
        value = value * rows(beta, hv)
    tr._add(L, idx[hv], value, bounce + 1, None, stats)


def unavailable(mode, clamp, transparency, lights, max_bounces):
    """Why a tracer of ``mode`` with the sample ``clamp`` (a ``SampleClamp`` or None), the
    scene's ``transparency`` (None: opaque), its ``lights`` (``EmitterSampler``) and path length
    ``max_bounces`` cannot join light vertices (a sentence), or None when it can."""
    if mode not in ("UNGUIDED", "GUIDED"):
        return f"{mode} has no light connections"
    if clamp is not None and clamp.active:
        return ("light connections off: a sample clamp is on (Cycles clamps its own path sampling; "
                "Clamp Direct / Indirect 0 turns them on)")
    if transparency is not None:
        return "light connections off: the scene has transparent (alpha) materials"
    if lights.empty:
        return "light connections off: no emissive mesh (lamps and the world keep their own sampling)"
    if max_bounces < 1:
        return "light connections off: no bounce"
    return None


def off_reason(scene, settings):
    """Why a bake of ``scene`` with ``settings`` traces no light connections although
    ``light_share`` > 0 in AUTO, UNGUIDED or GUIDED (a sentence for the report), or None (they are on,
    or not asked for): :func:`unavailable`, the tracer's own test."""
    from ..lights import EmitterSampler
    from ..transparency import Transparency
    from .clamp import SampleClamp
    mode = "UNGUIDED" if settings.bake_mode == "AUTO" else settings.bake_mode   # AUTO's parts trace both
    if settings.light_share <= 0 or mode not in ("UNGUIDED", "GUIDED"):
        return None
    return unavailable(mode, SampleClamp.from_settings(settings), Transparency.of(scene),
                       EmitterSampler(scene), settings.max_bounces)
