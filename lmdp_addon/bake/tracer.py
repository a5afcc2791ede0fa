"""Wavefront path tracer for indirect diffuse light at surface points (UNGUIDED, GUIDED, FINAL_GATHER).

The quantity is the one of Cycles' ``bake(type='DIFFUSE', pass_filter={'INDIRECT'})``: at a
shading point x with normal n,

    I(x) = E_ind(x) / π = (1/π) ∫_{H(n)} L_r(h(x, ω), -ω) cos θ dω,                 (thesis eq. 2.7)

the irradiance carried by light that has bounced at least once, without x's own albedo: the
emission of the surface hit by the first ray and light escaping to the world straight from x are
*direct* light and are left out, exactly as Cycles splits its passes. ``L_r(y)`` is the reflected
radiance at y = h(x, ω): ``ρ(y) [D(y) + I(y)]`` with D the direct light (emitters and world) and
I the indirect light at y, recursively.

Estimator (per path, all paths of a batch advance together: "wavefront"; no Python loop over rays):

* vertex 0 (the texel point) samples ω0 with pdf ``p0``; weight ``w0 = cos θ0 / (π p0)``;
* at every later vertex y_k (k = 1 .. max_bounces) the throughput is ``β_k = β_{k-1} w_{k-1} ρ(y_k)``
  and **next-event estimation** samples one point on the emitters with a shadow ray
  (:meth:`~lmdp_addon.lights.EmitterSampler.next_event`); one-sided emitters (area lights) count
  only on their front side, mesh emission on both (``SceneArrays``); Blender's lights (point,
  spot, sun and area lamps) add their light samples (:meth:`~lmdp_addon.lamps.Lamps.next_event`),
  MIS-weighted against the rays that hit the lamps with a body (``lamp_hits``; a ray crosses a
  lamp and goes on, as in Cycles);
* emitters hit by a ray sampled at y_k (k >= 1) are counted too, and the two estimates of the
  emitted light are combined by multiple importance sampling
  (:meth:`~lmdp_addon.lights.EmitterSampler.emission_hits`); the emitter hit by the texel's own
  first ray is direct light and is left out; a uniform world is counted only through sampled
  rays that escape from y_k (k >= 1), weight ``β_k w_k L_world``; an environment map (HDRI) is
  sampled at every y_k with a shadow ray to infinity as well and the two halves are combined by
  the balance heuristic (:func:`~lmdp_addon.world.next_event`,
  :func:`~lmdp_addon.world.escape_weight`);
* ``max_bounces`` = N keeps vertices y_1 .. y_N (NEE at each and the escape of y_N's ray), which
  is what Cycles' ``max_bounces = N`` (with ``diffuse_bounces >= N``) bakes: Cycles' kernel uses
  ``N + 1`` internally and stops shading at the vertex whose incoming bounce count reaches it;
* ``content`` (:mod:`~lmdp_addon.bake.content`) adds the direct light at the start point x0
  (NEE at x0 and the MIS-weighted emission / world its first ray finds: Cycles' {'DIRECT',
  'INDIRECT'}) and / or multiplies each path by x0's diffuse colour (Cycles' 'COLOR');
* Russian roulette from vertex ``rr_start`` on: survival probability ``min(1, max_c β_c)``,
  survivors divided by it (unbiased).
* **light connections** (``light_share`` s > 0, UNGUIDED and GUIDED without the clamp or
  transparency): with probability s a path also traces one light vertex y' (a point on the
  emitters ∝ power, a cosine direction from it, its first hit, :meth:`_light_subpaths`), and
  every Lambertian eye vertex is joined to it by a shadow ray (:meth:`_connect`); the light
  sample at y', the BSDF ray from y' that hits the emitter and the connection are weighted by the
  balance heuristic over the three (``px p_L / D``, ``px q / D``, ``s P_lt / D``; docs/design.md
  "Light connections"), so the estimate stays unbiased;
* ``clamp`` (:mod:`~lmdp_addon.bake.clamp`): Cycles' sample clamp of every contribution
  (:meth:`IndirectTracer._add`), and then Cycles' Russian roulette instead (from y_2, survival
  ``min(1, sqrt(max_c T_c))`` of Cycles' throughput T = ρ(x0) β w), so that the clamped
  contributions are distributed as Cycles'; guided directions enter the clamp through the
  ratio of Cycles' throughput to the path's (:func:`_to_cycles`).

Direction sampling (``guide.py``): UNGUIDED (and RESIDUAL) cosine-weighted, ``p(ω) = cos θ / π`` (``w = 1``);
GUIDED the one-sample mixture ``α g_s + (1 - α) cos θ / π`` of the optimal policy of the
nearest compatible state s and cosine sampling; FINAL_GATHER draws the first direction as GUIDED
and ends the path at its hit y_1 with the solution's ẑ_ind there (``gather.py``), the direct
light at y_1 by light sampling; the hits the gather cannot serve continue as GUIDED paths.
RESIDUAL traces UNGUIDED paths that also record the control variate g at their first hit
(``residual.py``), and its control samples stop there (``first_hit_only``).
At vertices on glossy surfaces (``SceneArrays.materials``) the BSDF of ``bsdf.VertexBSDF`` is
sampled instead (GUIDED: mixed with the guide), with its f cos and density in next-event
estimation and MIS, Cycles' Filter Glossy and its separate glossy bounce limit (docs/design.md).

Arrays are float32 in the hot loop (positions keep ~1e-7 relative precision). Hit points are
rebuilt from the hit's barycentrics on the hit triangle, so they lie on its plane to the
precision of its corners whatever the length of the ray, and every ray origin is offset along
the normal by ``RayCaster.offset`` of the triangle it leaves (8 float32 ulps of the magnitude
of the coordinates there, see ``raycast``): nothing far away changes the offsets of a room.
"""
from dataclasses import dataclass

import numpy as np

from .. import lamp_hits
from .. import world as world_light
from ..bsdf import GlossyRows, VertexBSDF
from ..lights import EmitterSampler
from ..raycast import RayCaster
from ..sampling import dot, rows, set_rows
from ..transparency import Transparency
from . import connections, reuse
from .clamp import clamp_light
from .content import BakeContent, times_color
from .guide import CosineDirections, GuidedDirections
from .splitting import window as splitting_window

MODES = ("UNGUIDED", "GUIDED", "FINAL_GATHER", "RESIDUAL")
INV_PI = 1.0 / np.pi
#: Largest guide share α at glossy vertices (:meth:`IndirectTracer._guided_glossy`): the guide
#: tabulates the light a diffuse lobe wants, and a glossy lobe's own samples matter more there
#: (measured on the glossy box at 64 samples, GUIDED without splitting: variance per path 16.4
#: at α = 0.5, 30.7 at 0.75).
GLOSSY_GUIDE_FRACTION = 0.5
LUMINANCE32 = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass
class TraceStats:
    """Work done by :meth:`IndirectTracer.trace` (summed over calls)."""

    paths: int = 0
    rays: int = 0             #: closest-hit rays
    shadow_rays: int = 0      #: NEE occlusion rays
    vertices: int = 0         #: path vertices shaded (y_1, y_2, ...)
    clamped: int = 0          #: light contributions scaled down by the sample clamp (``clamp``)
    guided_vertices: int = 0  #: vertices that had a compatible state (GUIDED / FINAL_GATHER)
    gathered: int = 0         #: FINAL_GATHER paths ended by the solution at y_1
    gather_fallback: int = 0  #: FINAL_GATHER paths continued by path tracing (no state near y_1)
    glossy_vertices: int = 0  #: vertices on surfaces with microfacet lobes (BSDF sampling)
    light_vertices: int = 0   #: light vertices traced for light connections
    connections: int = 0      #: light connections that reached their light vertex (shadow ray clear)
    shared_hits: int = 0      #: first hits of other texels' paths a texel could use (path reuse)

    def add(self, other):
        for name in self.__dataclass_fields__:
            setattr(self, name, getattr(self, name) + getattr(other, name))
        return self

    @property
    def total_rays(self):
        return self.rays + self.shadow_rays

    def as_dict(self):
        return {name: int(getattr(self, name)) for name in self.__dataclass_fields__}


class IndirectTracer:
    """Traces batches of paths from surface points and returns their indirect-light estimates.

    scene           the :class:`~lmdp_addon.scene_arrays.SceneArrays` that is traced
    mode            'UNGUIDED', 'GUIDED' or 'FINAL_GATHER'
    max_bounces     N: path vertices y_1..y_N after the shading point (Cycles' max_bounces)
    guide           :class:`~lmdp_addon.bake.guide.StateGuide` (GUIDED, FINAL_GATHER)
    gather          :class:`~lmdp_addon.bake.gather.GatherField` (FINAL_GATHER)
    guide_fraction  α of the mixture
    rr_start        first vertex index at which Russian roulette may end a path
    caster          the :class:`~lmdp_addon.raycast.RayCaster` to trace with (default: a new one)
    control         :class:`~lmdp_addon.bake.residual.ControlVariate` (RESIDUAL: cosine paths that
                    record the control variate g at their first hit, ``trace(control_out=...)``)
    content         :class:`~lmdp_addon.bake.content.BakeContent`: also the direct light at the
                    start point, and / or times its diffuse colour (default: indirect only)
    glossy_bounces, total_bounces  on glossy scenes, Cycles' Glossy and Max bounces: a path keeps
                    at most ``max_bounces`` diffuse, ``glossy_bounces`` glossy and
                    ``total_bounces`` bounces in all (-1: no separate limit, ``max_bounces``)
    light_share     s: the share of paths with a light vertex joined to their eye vertices (0: off)
    clamp           :class:`~lmdp_addon.bake.clamp.SampleClamp`: Cycles' direct / indirect sample
                    clamp on every light contribution (:meth:`_add`), with Cycles' Russian
                    roulette (:meth:`_cycles_roulette`) after ``min_light_bounces`` (Cycles' Min
                    Light Bounces); None or both limits 0: no clamp
    """

    def __init__(self, scene, mode="UNGUIDED", max_bounces=8, guide=None, gather=None,
                 guide_fraction=0.5, rr_start=3, caster=None, control=None, content=None,
                 glossy_bounces=-1, total_bounces=-1, clamp=None, min_light_bounces=0, light_share=0.0,
                 splitting=None, path_reuse=1):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, not {mode!r}")
        if mode in ("GUIDED", "FINAL_GATHER") and guide is None:
            raise ValueError(f"{mode} needs a StateGuide")
        if mode == "FINAL_GATHER" and gather is None:
            raise ValueError("FINAL_GATHER needs a GatherField")
        if mode == "RESIDUAL" and control is None:
            raise ValueError("RESIDUAL needs a ControlVariate")
        self.control = control if mode == "RESIDUAL" else None
        self.scene = scene
        self.mode = mode
        self.max_bounces = int(max_bounces)
        self.guide = guide if mode in ("GUIDED", "FINAL_GATHER") else None
        self.gather = gather if mode == "FINAL_GATHER" else None
        self.guide_fraction = float(np.clip(guide_fraction, 0.0, 1.0)) if self.guide is not None else 0.0
        self.directions = (GuidedDirections(self.guide, self.guide_fraction) if self.guide is not None
                           else CosineDirections())
        self.rr_start = int(rr_start)
        self.content = content or BakeContent()
        #: Cycles' sample clamp (None: off). It is a function of each contribution, so with it the
        #: paths also end by Cycles' Russian roulette, whose survivors carry Cycles' throughputs.
        self.clamp = clamp if clamp is not None and clamp.active else None
        #: Cycles' roulette spares the rays reaching y_k for k <= Min Light Bounces + 1.
        self.roulette_from = max(int(min_light_bounces), 0) + 2
        self.caster = caster or RayCaster(scene)
        self.lights = EmitterSampler(scene)
        self.lamps = scene.lamps
        #: Lamps with a body and Multiple Importance on: BSDF rays hit them (``lamp_hits``)
        self.lamp_hits = bool(np.any(self.lamps.hittable))
        corners = scene.corners()
        self.corner0 = corners[:, 0].astype(np.float32)
        self.edge1 = (corners[:, 1] - corners[:, 0]).astype(np.float32)
        self.edge2 = (corners[:, 2] - corners[:, 0]).astype(np.float32)
        self.offsets = self.caster.triangle_offset.astype(np.float32)
        self.face_normals = scene.triangle_geometry()[0].astype(np.float32)
        #: Smooth / custom normals: the shading normal N (BSDF, cosines) and the geometric
        #: normal Ng (side, ray offset) differ, and directions below Ng are absorbed (Cycles'
        #: ``bsdf_diffuse_sample``). Flat scenes keep the face normal for both, bit for bit.
        self.smooth = scene.has_smooth_normals()
        self.albedo = np.clip(scene.triangle_albedo, 0.0, 1.0).astype(np.float32)
        #: Textured materials: the albedo at each hit (``SceneArrays.albedo_at``); alpha: rays
        #: pass transparent surfaces with probability 1 - alpha (``transparency``).
        self.textured = scene.surface is not None and scene.surface.has_albedo
        self.transparency = Transparency.of(scene)
        #: Some surface may have a colour channel 0: the estimate there follows Cycles' pass
        #: division (``_even_colour``).
        self.zero_colour = bool(self.textured or self.transparency is not None
                                or np.any(self.albedo[~scene.is_emissive()] <= 0))
        self.objects = scene.triangle_object
        self.world = np.asarray(scene.world_radiance, dtype=np.float32)
        self.world_lit = bool(np.any(self.world > 0))
        #: An environment map (HDRI): escaping rays see L_env(ω) with an MIS weight and every
        #: vertex samples the world with a shadow ray (``world.py``); None: the uniform world.
        self.environment = scene.environment if getattr(scene, "environment", None) is not None \
            and scene.environment.lit else None
        #: World portals (``portals``): the map's light drawn by a probe's block probabilities,
        #: per region (``world_regions``: each triangle's row, None: one row for all).
        self.portals = None
        self.world_regions = None
        #: A :class:`~lmdp_addon.bake.portals.PortalProbe` that records the world samples (or None).
        self.world_probe = None
        #: Glossy surfaces (``SceneArrays.materials``): their vertices sample and evaluate the
        #: BSDF (``bsdf.VertexBSDF``); None: every surface is Lambertian (traced as before).
        self.glossy = scene.glossy_triangles() if scene.has_glossy() else None
        #: Cycles' Filter Glossy of the captured scene (``MaterialTable.filter_glossy``; 0: off):
        #: glossy lobes at a vertex get α ≥ 0.5 √(1 - p_min / filter), p_min the smallest density
        #: of the path's sampled rays so far (Cycles' ``surface_shader_prepare_closures``).
        self.filter_glossy = float(scene.materials.filter_glossy) if self.glossy is not None else 0.0
        #: Bounce limits of glossy scenes (Cycles' path_state_next): diffuse N, glossy, total.
        self.total_limit = max(int(total_bounces), self.max_bounces) if total_bounces >= 0 else self.max_bounces
        self.glossy_limit = int(glossy_bounces) if glossy_bounces >= 0 else self.total_limit
        if self.glossy is None:
            self.total_limit = self.max_bounces
        self.light_share = float(light_share) if connections.unavailable(
            mode, self.clamp, self.transparency, self.lights, self.max_bounces) is None else 0.0
        if self.light_share > 0:
            ok = (scene.triangle_geometry()[1] > 0) & ~scene.is_emissive()
            if self.glossy is not None:
                ok &= ~self.glossy
            self.connectable = ok
        #: The solution's Russian roulette and splitting (``splitting.SplitField``; None: the
        #: throughput roulette alone). Off with the clamp (Cycles' own roulette) and in the
        #: gather modes.
        self.splitting = splitting if (splitting is not None and self.clamp is None
                                       and mode in ("UNGUIDED", "GUIDED")) else None
        #: Path reuse (``reuse``): tiles of ``path_reuse`` x ``path_reuse`` texels share their
        #: first bounces (1: off; off with the clamp, transparency and the gather modes).
        self.path_reuse = max(int(path_reuse), 1) if reuse.unavailable(mode, self.clamp, self.transparency) is None \
            else 1

    def use_portals(self, portals):
        """Draw the environment map's light samples by the :class:`~lmdp_addon.bake.portals.Portals`
        ``portals`` from now on (None, or no environment map: the map's own sampling)."""
        if self.environment is None:
            return
        env = self.scene.environment
        self.portals = portals
        self.environment = env if portals is None else portals.sampler(env)
        self.world_regions = None if portals is None else portals.regions(self.scene)

    # ---- the wavefront loop ----------------------------------------------------------------------
    def trace(self, points, normals, states, u_first, u_mix, rng, triangles=None, control_out=None,
              first_hit_only=False, reuse_groups=None):
        """Estimates I(x) = E_ind/π for paths starting at ``points (n, 3)`` on surfaces with
        normals ``normals (n, 3)`` (the side that is baked).

        states   (n,) nearest compatible state of each start point (-1: none; ignored UNGUIDED)
        u_first  (n, 2) uniforms of the first direction (stratified by the caller)
        u_mix    (n,) uniforms choosing guide vs cosine at the first vertex
        rng      numpy Generator for everything else
        triangles  (n,) scene triangle of each start point, for its ray offset (None: the
                 largest offset of the scene, ``RayCaster.offset()``)
        control_out  (n, 3) float32 zeros (RESIDUAL): receives each path's control variate g at
                 its first hit (``residual``); ``first_hit_only``: stop there (control samples)
        reuse_groups (n,) the tile of each path (``reuse.groups``): with ``path_reuse`` > 1 the
                 paths of a tile share their first bounces (``reuse.combine``); None: each its own
        Returns ``(values (n, 3) float32, TraceStats)``; the mean of the values is unbiased for
        I (biased by the solution's discretisation in FINAL_GATHER).
        """
        n = len(points)
        stats = TraceStats(paths=n)
        L = np.zeros((n, 3), np.float32)
        if n == 0:
            return L, stats
        # ---- vertex 0: the texel point x and its first direction ω0 ----
        idx = np.arange(n)
        pos = start = np.ascontiguousarray(points, dtype=np.float32)
        nrm = np.ascontiguousarray(normals, dtype=np.float32)
        gnrm = nrm
        if self.smooth and triangles is not None:
            nrm, gnrm = self._start_normals(pos, nrm, np.asarray(triangles, dtype=np.int64))
        colour0 = None       # the diffuse colour at x (zero_colour, multiply_color, clamp)
        if (self.zero_colour or self.clamp is not None) and triangles is not None:
            # Cycles' DIFFUSE INDIRECT pass is divided by the diffuse colour at x (albedo x
            # alpha); in channels where that colour is 0 it takes the others' (below). Cycles'
            # clamp sees the light times it (its throughput after x, ``clamp``).
            colour0 = self._start_colour(pos, np.asarray(triangles, dtype=np.int64))
        # What the clamp multiplies each path's contributions by to see Cycles' own: ρ(x0) and,
        # where the guide draws directions, Cycles' throughput over the path's (``_to_cycles``).
        rho0 = None
        if self.clamp is not None:
            rho0 = colour0
            if self.guide is not None:
                rho0 = np.ones((n, 3), np.float32) if colour0 is None else colour0.astype(np.float32, copy=True)
        states = np.asarray(states, dtype=np.int64) if self.guide is not None else np.full(n, -1)
        d, w, cos_prev = self.directions.sample(nrm, states, np.asarray(u_first, np.float64),
                                                np.asarray(u_mix), first=True)
        w = self._above_geometry(w, gnrm, d)
        beta = np.ones((n, 3), np.float32)
        lift = (np.full(n, self.caster.offset(), np.float32) if triangles is None
                else np.take(self.offsets, triangles))
        first_bounce = None      # path reuse: x_0 and y_1 of every path (``reuse``)
        if reuse_groups is not None and self.path_reuse > 1 and control_out is None:
            first_bounce = reuse.FirstBounce(pos + lift[:, None] * gnrm, nrm, gnrm, states, w)
        reg = None     # the world portals' region of each path's current vertex
        if self.world_regions is not None:
            reg = np.zeros(n, np.int64) if triangles is None else np.take(self.world_regions, triangles)
        if self.content.direct:   # ---- direct light at x0: NEE here, MIS hits of ω0 below ----
            samples = self._light_samples(pos, nrm, gnrm, lift, rng, stats, regions=reg)
            self._add_light_samples(L, idx, None, samples, _summed(samples), 0, rho0, stats)
        if rho0 is not None and self.guide is not None:   # ω0's weight: from here on in Cycles' terms
            _to_cycles(rho0, idx, _cosine_ratio(w))
        paths = None
        if self.splitting is not None:   # V(s_0): the texel's expected light, the window's unit
            if self.guide is None and triangles is not None:
                paths = _Paths(self.splitting.at_points(start, gnrm, np.take(self.objects, triangles)))
            elif self.guide is not None:
                paths = _Paths(self.splitting.at_states(states))
        lv = joins = None      # light connections (``connections``)
        if self.light_share > 0:
            lv = connections.LightVertices(self, n, rng, stats)
            joins = connections.JoinState(n, self.light_share, self.lights)
            if first_bounce is None:    # with path reuse the tile draws y_1: x_0 is not joined
                connections.connect(self, L, lv, idx, pos, nrm, gnrm, lift, None, states, True, 0, stats)
                joins.joined[idx] = True
        idx, pos, nrm, gnrm, lift, d, w, cos_prev, beta, reg = _select_rows(np.flatnonzero(w > 0), idx, pos, nrm,
                                                                            gnrm, lift, d, w, cos_prev, beta, reg)
        # Filter Glossy: the smallest (unguided, Cycles' min_ray_pdf) density of the path's rays
        p_min = (np.maximum(cos_prev, 0.0) * INV_PI).astype(np.float32) if self.filter_glossy > 0 else None
        n_glossy = np.zeros(len(idx), np.int16) if self.glossy is not None else None   # glossy bounces
        bounce = 1
        q_prev = None
        while len(idx):
            # ---- closest hits y_bounce of the sampled directions ----
            origin = pos + lift[:, None] * gnrm
            if self.transparency is None:
                tri, dist, bu, bv = self.caster.intersect(origin, d, barycentrics=True)
            else:
                tri, dist, bu, bv, passes, tint = self.transparency.intersect(self.caster, origin, d, rng)
                stats.rays += passes
                if tint is not None:     # the colour of the tinted surfaces passed
                    beta = beta * tint
            stats.rays += len(idx)
            h = np.flatnonzero(tri >= 0)
            hook = None
            if joins is not None:   # the emitter hits' share (of the vertex left), then move on
                hook = joins.emission_hook(idx, gnrm, d)
                joins.arrive(self, idx, h, d, w, cos_prev, tri, dist)
            if bounce >= 2 or self.content.direct:
                self._light_found(L, idx, beta * w[:, None], origin, d, tri, dist, cos_prev, h, q_prev,
                                  bounce=bounce, rho0=rho0, stats=stats, mis_hook=hook, regions=reg)
                if self.lamp_hits:   # lamps the rays cross before their hit (they go on through)
                    self._lamps_found(L, idx, beta * w[:, None], origin, nrm, d, tri, dist, cos_prev, q_prev,
                                      bounce=bounce, rho0=rho0, stats=stats)
            if first_bounce is not None and bounce == 1 and self.content.direct:
                first_bounce.direct = L.copy()       # x_0's own light, kept out of the reuse
            if bounce > self.total_limit:
                break
            if n_glossy is not None:   # Cycles' diffuse and glossy limits (the texel's bounce is diffuse)
                within = ((bounce - n_glossy) <= self.max_bounces) & (n_glossy <= self.glossy_limit)
                h = h[within[h]]
            # ---- the vertex y_bounce: β_k = β_{k-1} w_{k-1} ρ(y_k) ----
            # (the origins are not needed past this point; the distances only at y_1 by the gather)
            dist = np.take(dist, h) if bounce == 1 and (control_out is not None or self.gather is not None) else None
            idx, d, w, beta, tri, bu, bv = _select_rows(h, idx, d, w, beta, tri, bu, bv)
            p_min, n_glossy = _take(p_min, h), _take(n_glossy, h)
            if self.clamp is not None and bounce >= self.roulette_from:   # Cycles' roulette before y_bounce
                keep, p_keep = self._cycles_roulette(idx, beta, w, rho0, rng)
                idx, d, w, beta, tri, dist, bu, bv = _select_rows(keep, idx, d, w, beta, tri, dist, bu, bv)
                beta = beta / p_keep[:, None]
                p_min, n_glossy = _take(p_min, keep), _take(n_glossy, keep)
                if len(idx) == 0:
                    break
            pos, nrm, gnrm, front, beta_hit = self._vertices(d, tri, bu, bv, w, beta)
            glossy = None if self.glossy is None else np.flatnonzero(self.glossy[tri])
            if glossy is not None and len(glossy):
                # β_k = β_{k-1} w_{k-1}: the BSDF's weight f cos / p joins when ω_k is sampled
                beta_hit[glossy] = rows(beta, glossy) * rows(w, glossy)[:, None]
            beta = beta_hit
            if first_bounce is not None and bounce == 1:
                first_bounce.arrive(idx, pos, gnrm, tri, None if self.glossy is None else self.glossy[tri])
            wi = -d if self.glossy is not None else None   # the view direction of glossy vertices
            lift = np.take(self.offsets, tri)
            stats.vertices += len(idx)
            objs = np.take(self.objects, tri)
            reg = None if self.world_regions is None else np.take(self.world_regions, tri)
            z_ind = None
            if bounce == 1 and control_out is not None:    # RESIDUAL: ẑ_ind(y_1) of g
                z_ind = self.control.indirect_at(tri, bu, bv, pos, gnrm, front, objs, dist)
            if bounce == 1 and self.gather is not None:
                live = self._final_gather(L, idx, pos, nrm, gnrm, lift, beta, tri, bu, bv, dist, front, objs,
                                          rng, stats, rho0, reg)
                idx, pos, nrm, gnrm, lift, beta, tri, bu, bv, front, objs, wi, reg = _select_rows(
                    live, idx, pos, nrm, gnrm, lift, beta, tri, bu, bv, front, objs, wi, reg)
                p_min, n_glossy = _take(p_min, live), _take(n_glossy, live)
            alive = _channel_max(beta) > 0
            if not np.all(alive):
                idx, pos, nrm, gnrm, lift, beta, tri, bu, bv, front, objs, wi, reg = _select_rows(
                    np.flatnonzero(alive), idx, pos, nrm, gnrm, lift, beta, tri, bu, bv, front, objs, wi, reg)
                p_min, n_glossy = _take(p_min, np.flatnonzero(alive)), _take(n_glossy, np.flatnonzero(alive))
                z_ind = z_ind[alive] if z_ind is not None else None
            if len(idx) == 0:
                break
            vstates = np.full(len(idx), -1, dtype=np.int64)
            glossy_rows = self._glossy_rows(tri, bu, bv, nrm, gnrm, wi, stats, p_min)
            if self.guide is not None:
                vstates = self.guide.states_at_hits(tri, bu, bv, pos, gnrm, front, objs)
                stats.guided_vertices += int(np.count_nonzero(vstates >= 0))
            elif paths is not None:   # the window's own lookup (the guide's states serve GUIDED)
                vstates = self.splitting.states_at_hits(tri, bu, bv, pos, gnrm, front, objs)
            # ---- next-event estimation at y_bounce ----
            record = None
            if self.world_probe is not None:     # a portal probe: its world samples, weighed by β
                record = self.world_probe.recorder(tri, beta @ LUMINANCE32)
            samples = self._light_samples(pos, nrm, gnrm, lift, rng, stats, glossy_rows,
                                          hook=None if joins is None else joins.hook(idx), regions=reg,
                                          record=record)
            direct = _summed(samples)
            self._add_light_samples(L, idx, beta, samples, direct, bounce, rho0, stats)
            if joins is not None:    # light vertices joined to y_bounce (a vertex bounce + 1)
                eligible = self._joinable(bounce, n_glossy, glossy_rows, len(idx))
                joins.joined[idx] = eligible
                e = np.flatnonzero(eligible)
                if len(e):
                    connections.connect(self, L, lv, idx[e], rows(pos, e), rows(nrm, e), rows(gnrm, e),
                                        np.take(lift, e), rows(beta, e), np.take(vstates, e), False, bounce, stats)
            if z_ind is not None:    # g = β_1 (D̂(y_1) + ẑ_ind(y_1)) on the path's own light sample
                control_out[idx] = beta * (direct + z_ind)
                if first_hit_only:
                    break
            # ---- Russian roulette (with the clamp: Cycles', above) and splitting ----
            if paths is not None:
                L, rr = paths.window(self, L, idx, beta, vstates, bounce, rng, joins, lv)
                idx, beta, keep = rr       # rows: increasing, repeated for the copies
                pos, nrm, gnrm, lift, vstates, reg = _taken_rows(keep, pos, nrm, gnrm, lift, vstates, reg)
                p_min, n_glossy = _take(p_min, keep), _take(n_glossy, keep)
                if glossy_rows is not None:
                    glossy_rows = glossy_rows.select(keep)
                if len(idx) == 0:
                    break
            elif bounce >= self.rr_start and self.clamp is None:
                q = np.minimum(_channel_max(beta), 1.0)
                survive = np.flatnonzero(rng.random(len(idx), dtype=np.float32) < q)
                beta = rows(beta, survive) / q[survive, None]
                idx, pos, nrm, gnrm, lift, vstates, reg = _select_rows(survive, idx, pos, nrm, gnrm, lift, vstates,
                                                                       reg)
                p_min, n_glossy = _take(p_min, survive), _take(n_glossy, survive)
                if glossy_rows is not None:
                    glossy_rows = glossy_rows.select(survive)
                if len(idx) == 0:
                    break
            # ---- the next direction ω_bounce ----
            u = rng.random((len(idx), 3))
            glossy_states = None
            if glossy_rows is not None and self.guide is not None:
                glossy_states = vstates
                vstates = np.where(glossy_rows.mask, -1, vstates)   # the guide mixes with the BSDF there
            d, w, cos_prev = self.directions.sample(nrm, vstates, u[:, :2], u[:, 2], first=False)
            w = self._above_geometry(w, gnrm, d)
            q_prev = None
            ratio = None
            if rho0 is not None and self.guide is not None:
                ratio = _cosine_ratio(w)
            if glossy_rows is not None:
                d, w, beta, q_prev, lobe = self._sample_glossy(glossy_rows, u, d, w, beta, glossy_states,
                                                               cycles_ratio=ratio)
                n_glossy = n_glossy + lobe
            if ratio is not None:
                _to_cycles(rho0, idx, ratio)
            if p_min is not None:
                p_ray = np.maximum(cos_prev, 0.0) * INV_PI
                if q_prev is not None:
                    p_ray = np.where(np.isnan(q_prev), p_ray, q_prev)
                p_min = np.minimum(p_min, p_ray).astype(np.float32)
            keep = w > 0
            if not np.all(keep):
                keep = np.flatnonzero(keep)
                idx, pos, nrm, gnrm, lift, d, w, cos_prev, beta, reg = _select_rows(
                    keep, idx, pos, nrm, gnrm, lift, d, w, cos_prev, beta, reg)
                if q_prev is not None:
                    q_prev = np.take(q_prev, keep)
                p_min, n_glossy = _take(p_min, keep), _take(n_glossy, keep)
            bounce += 1
        if paths is not None:
            L = paths.gathered(L)
        if first_bounce is not None:
            L = reuse.combine(self, first_bounce, L, reuse_groups, stats)
        if self.zero_colour and triangles is not None:
            L = _even_colour(L, colour0)
        if self.content.multiply_color:   # Cycles' COLOR filter: times the diffuse colour at x
            if triangles is None:
                raise ValueError("multiply_color needs the start points' triangles")
            times_color(L, colour0 if colour0 is not None
                        else self._start_colour(start, np.asarray(triangles, dtype=np.int64)))
        return L, stats

    def _start_colour(self, pos, triangles):
        """(k, 3) diffuse colour (albedo x alpha) of the start points ``pos`` on ``triangles``."""
        t = triangles
        bu, bv = (x.astype(np.float32) for x in self._barycentrics(pos, t))
        colour = self.scene.albedo_at(t, bu, bv)
        if self.transparency is not None:
            colour = colour * self.scene.surface.alpha(t, bu, bv)[:, None]
        return colour

    def _joinable(self, bounce, n_glossy, glossy_rows, k):
        """(k,) bool: the vertices y_bounce that may be joined to a light vertex (a path vertex
        bounce + 1): Lambertian and within the bounce limits."""
        ok = np.full(k, bounce + 1 <= self.total_limit)
        if n_glossy is not None:
            ok &= (bounce + 1 - n_glossy) <= self.max_bounces
        if glossy_rows is not None:
            ok &= ~glossy_rows.mask
        return ok

    def _light_samples(self, pos, nrm, gnrm, lift, rng, stats, glossy_rows=None, hook=None, regions=None,
                       record=None):
        """The light-sampling half of the direct light D(y) at the points ``pos`` (shading
        normals ``nrm``, geometric ``gnrm``, ray offsets ``lift``), one (k, 3) estimate per light
        kind: the emitters' MIS estimate (``lights``), Blender's lights (``lamps``; MIS-weighted
        where rays hit them) and the environment map's MIS estimate (``world``), in that order of
        random numbers (D(y) is their sum, :func:`_summed`); rows of ``glossy_rows``
        (:class:`~lmdp_addon.bsdf.GlossyRows`) shade with their BSDF's f cos and density;
        ``regions`` (k,): the world portals' region of each point (None: one for all),
        ``record``: a portal probe's recorder of the world samples (``world.next_event``)."""
        geometric = gnrm if self.smooth else None
        direct, shadow_rays = self.lights.next_event(pos, nrm, rng, self.caster, lift=lift, geometric=geometric,
                                                     bsdf=glossy_rows, mis_hook=hook)
        stats.shadow_rays += shadow_rays
        samples = [direct]
        if not self.lamps.empty:
            lamp_direct, shadow_rays = self.lamps.next_event(pos, nrm, rng, self.caster, lift=lift,
                                                             geometric=geometric, transparency=self.transparency,
                                                             bsdf=glossy_rows, mis=True)
            stats.shadow_rays += shadow_rays
            samples.append(lamp_direct)
        if self.environment is not None:
            world_direct, shadow_rays = world_light.next_event(self.environment, pos, nrm, rng, self.caster, lift,
                                                               geometric=geometric, transparency=self.transparency,
                                                               bsdf=glossy_rows, regions=regions, record=record)
            stats.shadow_rays += shadow_rays
            samples.append(world_direct)
        return samples

    # ---- Cycles' sample clamp ----------------------------------------------------------------------
    def _add(self, L, at, light, bounce, rho0, stats):
        """``L[at] += light``: one light contribution per row (throughput x light, after MIS),
        through Cycles' sample clamp when it is on (``clamp.clamp_light``: the limit of
        ``bounce``, 0 for light reaching x0 directly; the rows' ρ(x0) ``rho0[at]`` as the
        throughput the values leave out). Every contribution of the tracer goes through here."""
        if self.clamp is not None:
            light, count = clamp_light(light, self.clamp.limit(bounce), None if rho0 is None else rows(rho0, at))
            stats.clamped += count
        _add_rows(L, at, light)

    def _add_light_samples(self, L, at, beta, samples, direct, bounce, rho0, stats):
        """The light samples ``samples`` (:meth:`_light_samples`, summed ``direct``) of the paths
        ``at`` times their throughput ``beta`` (None: 1) into ``L``: with the clamp each light
        kind's sample is a contribution of its own (Cycles clamps each light sample)."""
        if self.clamp is None:
            self._add(L, at, direct if beta is None else beta * direct, bounce, rho0, stats)
            return
        for sample in samples:
            self._add(L, at, sample if beta is None else beta * sample, bounce, rho0, stats)

    def _cycles_roulette(self, idx, beta, w, rho0, rng):
        """Cycles' Russian roulette of the rays that reach y_k, k >= Min Light Bounces + 2
        (``intersect_closest``, ``path_state_continuation_probability``): survival probability
        ``p = min(1, sqrt(max_c T_c))`` of Cycles' throughput T = ρ(x0) β_{k-1} w_{k-1}, the
        survivors' β divided by p before y_k is shaded. Returns ``(surviving rows, their p)``.
        With the clamp the paths' throughputs must be Cycles' own: the clamp is nonlinear."""
        T = beta * w[:, None]
        if rho0 is not None:
            T = T * rows(rho0, idx)
        p = np.minimum(np.sqrt(_channel_max(np.abs(T))), 1.0).astype(np.float32)
        keep = np.flatnonzero(rng.random(len(idx), dtype=np.float32) < p)
        return keep, p[keep]

    def _barycentrics(self, pos, t):
        """Barycentrics ``(bu, bv)`` (k,) float64 of the points ``pos`` (k, 3) in the planes of
        triangles ``t`` (least squares on the edges; 0 for degenerate triangles)."""
        e1, e2 = self.edge1[t].astype(np.float64), self.edge2[t].astype(np.float64)
        r = pos.astype(np.float64) - self.corner0[t]
        a, b, c = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
        p, q = (e1 * r).sum(1), (e2 * r).sum(1)
        det = a * c - b * b
        det = np.where(det != 0, det, 1.0)
        return (c * p - b * q) / det, (a * q - b * p) / det

    def _start_normals(self, pos, normals, triangles):
        """Shading and geometric normals ``(N, Ng)`` (k, 3) float32 of the start points ``pos``
        on ``triangles``, on the side of the given ``normals`` (the baked side): Ng the face
        normal, N the corner normals interpolated at the points' barycentrics (recomputed from
        the positions, so a jittered footprint point gets the normal Cycles gives it)."""
        ng = rows(self.face_normals, triangles)
        side = dot(ng, normals) >= 0
        ng = np.where(side[:, None], ng, -ng)
        smooth = np.flatnonzero(self.scene.smooth_triangles()[triangles])
        nrm = ng.copy()
        if len(smooth):
            t = triangles[smooth]
            bu, bv = self._barycentrics(pos[smooth], t)
            nrm[smooth] = self.scene.shading_normals(t, bu, bv, side=side[smooth])
        return nrm, ng

    def _above_geometry(self, w, gnrm, d):
        """``w`` with the directions below the geometric surface set to 0 (smooth scenes only):
        Cycles' diffuse BSDF samples about the shading normal and rejects (absorbs) directions
        with ``Ng · ω <= 0``, so the light they would carry is not part of the estimate."""
        if not self.smooth:
            return w
        return np.where(dot(gnrm, d) > 0, w, np.float32(0.0)).astype(w.dtype, copy=False)

    def _vertices(self, d, tri, bu, bv, w, beta):
        """The hit points y_k of rays in directions ``d`` on triangles ``tri`` at barycentrics
        ``(bu, bv)`` (:meth:`hit_points`: positions, shading and geometric normals of the side
        the ray arrived on, whether that is the front) and the throughput
        ``β_k = β_{k-1} w_{k-1} ρ(y_k)``."""
        pos, nrm, gnrm, front, albedo = self.hit_points(d, tri, bu, bv)
        return pos, nrm, gnrm, front, beta * (w[:, None] * albedo)

    def hit_points(self, d, tri, bu, bv):
        """Hits of rays in directions ``d`` on triangles ``tri`` at barycentrics ``(bu, bv)``:
        positions (``c0 + u e1 + v e2``, on the triangle to the precision of its corners), the
        shading normal N and the geometric normal Ng of the side the ray arrived on (both
        flipped on a back face, as Cycles does; N = Ng on flat triangles), whether that is the
        front, and the diffuse albedo there."""
        pos = rows(self.corner0, tri)                     # c0 + u e1 + v e2, in place
        pos += rows(self.edge1, tri) * bu[:, None]
        pos += rows(self.edge2, tri) * bv[:, None]
        gnrm = rows(self.face_normals, tri)
        front = dot(gnrm, d) < 0
        np.negative(gnrm, out=gnrm, where=~front[:, None])     # Ng of the side the ray arrived on
        nrm = self.scene.shading_normals(tri, bu, bv, side=front) if self.smooth else gnrm
        albedo = self.scene.albedo_at(tri, bu, bv) if self.textured else rows(self.albedo, tri)
        return pos, nrm, gnrm, front, albedo

    def _light_found(self, L, idx, bw, origin, d, tri, dist, cos_prev, h, q_prev=None, bounce=2, rho0=None,
                     stats=None, mis_hook=None, regions=None):
        """Adds to ``L`` the light found by the directions sampled at y_{k-1} (k = ``bounce`` >= 2,
        or 1 with the direct light of ``content``): the world through the rays that escape, the
        emitters through the rays ``h`` that hit geometry (the sampled-ray half of the MIS
        estimate); ``bw = β w`` of the rays; ``q_prev``: the BSDF density of rays sampled at glossy
        vertices (NaN elsewhere), or None; ``regions``: the world portals' region of the vertices
        the rays left (None: one for all). Contributions of bounce k - 1 (:meth:`_add`)."""
        stats = stats if stats is not None else TraceStats()
        if self.environment is not None and len(h) < len(idx):
            miss = np.flatnonzero(tri == -1)   # not the rays absorbed by transparency
            self._add(L, idx[miss], rows(bw, miss) * world_light.escape_weight(
                self.environment, rows(d, miss), np.take(cos_prev, miss),
                pdf_from=None if q_prev is None else np.take(q_prev, miss),
                regions=None if regions is None else np.take(regions, miss)), bounce - 1, rho0, stats)
        elif self.world_lit and len(h) < len(idx):
            miss = np.flatnonzero(tri == -1)   # not the rays absorbed by transparency
            self._add(L, idx[miss], rows(bw, miss) * self.world, bounce - 1, rho0, stats)
        if len(h):
            lit, value = self.lights.emission_hits(origin, d, tri, dist, cos_prev, h, self.face_normals,
                                                   pdf_from=q_prev, mis_hook=mis_hook)
            self._add(L, idx[lit], rows(bw, lit) * value, bounce - 1, rho0, stats)

    def _lamps_found(self, L, idx, bw, origin, nrm, d, tri, dist, cos_prev, q_prev=None, bounce=2, rho0=None,
                     stats=None):
        """Adds to ``L`` the sampled-ray half of the lamps' MIS estimate (``lamp_hits``): the
        lamps that the rays from the vertices at ``origin`` (shading normals ``nrm``) cross
        before their closest hit ``dist`` (suns: the rays that escape); ``bw = β w``.
        Contributions of bounce k - 1 (:meth:`_add`), as :meth:`_light_found`."""
        stats = stats if stats is not None else TraceStats()
        lit, value = lamp_hits.emission_hits(self.lamps, origin, nrm, d, np.where(tri >= 0, dist, np.inf),
                                             tri == -1, cos_prev, pdf_from=q_prev)
        self._add(L, idx[lit], rows(bw, lit) * value, bounce - 1, rho0, stats)

    def _final_gather(self, L, idx, pos, nrm, gnrm, lift, beta, tri, bu, bv, dist, front, objs, rng, stats,
                      rho0=None, regions=None):
        """FINAL_GATHER at y_1: the radiance leaving it, ρ (ẑ_ind + D_e), with the direct part by
        light sampling at y_1 itself (``gather.build_gather``), ends the paths the gather serves;
        returns the rows of the others (no state near, back faces, hits too close), which go on.
        ``nrm`` / ``gnrm``: the shading and geometric normals of the hit side. With the clamp the
        light samples at y_1 are clamped as Cycles' (bounce 1); ẑ_ind, the solution's expected
        light beyond y_1, is not a sample and is added as it is (``checks`` warns)."""
        value = self.gather.value_at(tri, bu, bv, pos, gnrm, front, objs)
        done = ~np.isnan(value[:, 0]) & ~self.gather.too_close(dist, objs)
        if self.glossy is not None:   # ẑ is Lambertian radiance: glossy hits go on as paths
            done &= ~self.glossy[tri]
        g = np.flatnonzero(done)
        direct, shadow_rays = self.lights.direct_light(rows(pos, g), rows(nrm, g), rng, self.caster,
                                                       lift=np.take(lift, g),
                                                       geometric=rows(gnrm, g) if self.smooth else None)
        stats.shadow_rays += shadow_rays
        samples = [direct]
        if self.environment is not None:   # the world's direct light at y_1 (ẑ then leaves it out)
            world_direct, shadow_rays = world_light.next_event(
                self.environment, rows(pos, g), rows(nrm, g), rng, self.caster, np.take(lift, g),
                geometric=rows(gnrm, g) if self.smooth else None, mis=False, transparency=self.transparency,
                regions=None if regions is None else np.take(regions, g))
            stats.shadow_rays += shadow_rays
            direct = direct + world_direct
            samples.append(world_direct)
        if not self.lamps.empty:
            lamp_direct, shadow_rays = self.lamps.direct_light(rows(pos, g), rows(nrm, g), rng, self.caster,
                                                               lift=np.take(lift, g),
                                                               geometric=rows(gnrm, g) if self.smooth else None,
                                                               transparency=self.transparency)
            stats.shadow_rays += shadow_rays
            direct = direct + lamp_direct
            samples.append(lamp_direct)
        if self.clamp is None:
            L[idx[g]] += rows(beta, g) * (value[g].astype(np.float32) + direct)
        else:
            L[idx[g]] += rows(beta, g) * value[g].astype(np.float32)
            self._add_light_samples(L, idx[g], rows(beta, g), samples, direct, 1, rho0, stats)
        stats.gathered += int(done.sum())
        stats.gather_fallback += int((~done).sum())
        return np.flatnonzero(~done)


    def _guided_glossy(self, vertex, u, states, cycles_ratio=None):
        """GUIDED at glossy vertices (:meth:`_sample_glossy`): ``(wo, f cos / p, q, lobe kind)``
        with p = α g_s + (1 - α) p_bsdf at rows with a state (exact; a mirror lobe's sample
        keeps its delta weight / (1 - α)) and the BSDF alone elsewhere; q is the BSDF density.
        ``cycles_ratio`` (k,): receives p / p_bsdf (the mirror's 1 - α), Cycles' weight over
        this one, at the rows with a state (the clamp's view, :func:`_to_cycles`). α is
        ``guide_fraction`` up to :data:`GLOSSY_GUIDE_FRACTION`."""
        alpha = min(self.guide_fraction, GLOSSY_GUIDE_FRACTION)
        has = states >= 0
        guided = has & (u[:, 2] < alpha)
        ub = np.array(u, dtype=np.float64)
        rescale = has & ~guided
        ub[rescale, 2] = (ub[rescale, 2] - alpha) / max(1.0 - alpha, 1e-12)
        wo, weight, pdf, kind = vertex.sample(ub, return_lobe=True)
        gi = np.flatnonzero(guided)
        if len(gi):
            wo[gi] = self.guide.sample(states[gi], ub[gi, :2], first=False)
            kind[gi] = 0          # a guided bounce counts as diffuse
        mix = np.flatnonzero(has & (kind < 2))
        if len(mix):
            f, p_bsdf = vertex.eval(wo[mix], mix)
            g_s = self.guide.density(states[mix], wo[mix].astype(np.float32), first=False)
            p_mix = alpha * g_s + (1.0 - alpha) * p_bsdf
            above = np.sum(vertex.ng[mix] * wo[mix], axis=1) > 0
            ok = above & (p_mix > 0) & (np.isin(mix, gi) | (pdf[mix] > 0))
            weight[mix] = np.where(ok[:, None], f / np.where(p_mix > 0, p_mix, 1.0)[:, None], 0.0)
            pdf[mix] = np.where(ok, np.maximum(p_bsdf, 1e-30), 0.0)
            if cycles_ratio is not None:
                cycles_ratio[mix] = np.where(ok, p_mix / np.maximum(p_bsdf, 1e-30), 1.0)
        mirror = np.flatnonzero(has & (kind == 2))
        if len(mirror):
            weight[mirror] /= max(1.0 - alpha, 1e-12)
            if cycles_ratio is not None:
                cycles_ratio[mirror] = max(1.0 - alpha, 1e-12)
        return wo, weight, pdf, kind

    # ---- glossy vertices ----------------------------------------------------------------------------
    def _glossy_rows(self, tri, bu, bv, nrm, gnrm, wi, stats, p_min=None):
        """The :class:`~lmdp_addon.bsdf.GlossyRows` of the vertices on glossy triangles ``tri`` at
        barycentrics ``(bu, bv)`` (their BSDF set up for the view directions ``wi`` with the
        diffuse colour at the hit, blurred by Filter Glossy from the paths' smallest ray
        densities ``p_min``), or None when there are none."""
        if self.glossy is None:
            return None
        g = np.flatnonzero(self.glossy[tri])
        if len(g) == 0:
            return None
        stats.glossy_vertices += len(g)
        t = np.take(tri, g)
        blur = None
        if p_min is not None:
            blur_pdf = np.take(p_min, g).astype(np.float64) / self.filter_glossy
            blur = np.where(blur_pdf < 1.0, np.sqrt(np.maximum(1.0 - blur_pdf, 0.0)) * 0.5, 0.0)
        albedo = (self.scene.albedo_at(t, np.take(bu, g), np.take(bv, g)) if self.textured
                  else rows(self.albedo, t))
        vertex = VertexBSDF(self.scene.materials, np.take(self.scene.triangle_material, t), albedo,
                            rows(nrm, g), rows(wi, g), geometric=rows(gnrm, g), blur=blur)
        return GlossyRows(len(tri), g, vertex)

    def _sample_glossy(self, glossy_rows, u, d, w, beta, states=None, cycles_ratio=None):
        """Directions of the glossy rows drawn from their BSDF (``u``: their uniforms), or in
        GUIDED mode at rows with a state (``states`` of the wavefront, -1: none) from the
        one-sample mixture ``α g_s + (1 - α) p_bsdf`` (α at most :data:`GLOSSY_GUIDE_FRACTION`;
        u[:, 2] < α picks the guide, else it is rescaled to pick the lobe): the weight
        ``f cos / p`` joins β (w = 1, 0 when absorbed); returns ``(d, w, beta, q, lobe)`` with q
        (k,) float32 the BSDF density of those rays (NaN on the other rows; the MIS partition of
        unity, as next-event estimation uses it) and
        lobe (k,) int16 1 where a microfacet lobe was sampled (a glossy bounce). ``cycles_ratio``
        (k,) float32: its glossy rows are set to Cycles' weight over theirs (1 without a guide)."""
        g = np.flatnonzero(glossy_rows.mask)
        ratio = None if cycles_ratio is None else np.ones(len(g), np.float64)
        if states is not None and np.any(np.take(states, g) >= 0):
            wo, weight, pdf, kind = self._guided_glossy(glossy_rows.bsdf, rows(u, g), np.take(states, g), ratio)
        else:
            wo, weight, pdf, kind = glossy_rows.bsdf.sample(rows(u, g), return_lobe=True)
        if cycles_ratio is not None:
            cycles_ratio[g] = ratio
        microfacet = kind > 0
        d = d.copy()
        d[g] = wo
        w = w.copy()
        w[g] = np.where((pdf > 0) & (weight.max(axis=1) > 0), 1.0, 0.0)
        beta = beta.copy()
        beta[g] = rows(beta, g) * weight
        q = np.full(len(d), np.nan, np.float32)
        q[g] = pdf
        lobe = np.zeros(len(d), np.int16)
        lobe[g] = microfacet
        return d, w, beta, q, lobe


class _Paths:
    """The paths of one :meth:`IndirectTracer.trace` call when the solution's window splits them:
    copies get path numbers of their own beyond the n texel paths (their light, light vertex
    and balance-heuristic state are per path number), ``owner`` the texel path of each."""

    def __init__(self, v0):
        self.n = len(v0)
        self.owner = np.arange(self.n)
        self.v0 = v0

    def window(self, tr, L, idx, beta, vstates, bounce, rng, joins, lv):
        """``(L, (idx, beta, rows))``: the window of ``splitting`` at the vertices (states
        ``vstates``) of the paths ``idx`` (the throughput roulette where V is unknown): the
        rows kept ``rows`` (increasing, repeated for copies), the paths' numbers (copies get new
        ones) and the survivors' β."""
        v = tr.splitting.at_states(vstates)
        v0 = np.take(self.v0, idx)
        known = (v > 0) & (v0 > 0)
        lum = beta @ LUMINANCE32
        ratio = np.where(known, lum * v / np.where(known, v0, 1.0), 0.0)
        roulette = bounce >= tr.rr_start
        p, copies = splitting_window(ratio, known, np.full(len(idx), roulette), rng)
        if roulette:    # the throughput roulette where the solution says nothing
            p = np.where(known, p, np.minimum(_channel_max(beta), 1.0))
        u = rng.random(len(idx))
        survive = np.flatnonzero(u < p)
        n = copies[survive]
        scale = (1.0 / (p[survive] * n)).astype(np.float32)
        if np.all(n == 1):     # no copies: the survivors alone
            return L, (np.take(idx, survive), np.take(beta, survive, axis=0) * scale[:, None], survive)
        keep = np.repeat(survive, n)
        beta = np.take(beta, keep, axis=0) * np.repeat(scale, n)[:, None]
        new_idx = np.take(idx, keep)
        extra = np.flatnonzero(np.r_[False, keep[1:] == keep[:-1]])
        if len(extra):      # copies after the first: new path numbers
            parents = new_idx[extra]
            first_new = len(self.owner)
            new_idx[extra] = first_new + np.arange(len(extra))
            self.owner = np.concatenate([self.owner, np.take(self.owner, parents)])
            self.v0 = np.concatenate([self.v0, np.take(self.v0, parents)])
            L = np.concatenate([L, np.zeros((len(extra), 3), np.float32)])
            if joins is not None:
                joins.extend(parents)
                lv.extend(parents)
        return L, (new_idx, beta, keep)

    def gathered(self, L):
        """The (n, 3) light of the texel paths: each copy's added to its texel path's."""
        if len(self.owner) == self.n:
            return L
        out = L[:self.n].copy()
        np.add.at(out, self.owner[self.n:], L[self.n:])
        return out


def _cosine_ratio(w):
    """Cycles' weight over the path's for directions drawn with weights ``w (k,)``: Cycles draws
    cosine directions (weight 1) where the guide's have w = cos θ / (π p), so 1 / w = p / (cos θ
    / π) (1 where w = 0: those paths end)."""
    return np.where(w > 0, 1.0 / np.where(w > 0, w, 1.0), 1.0).astype(np.float32)


def _to_cycles(weights, idx, ratio):
    """The clamp's weights of the paths ``idx`` (rows of ``weights (n, 3)``, in place) times
    ``ratio (k,)``, Cycles' throughput over theirs for the directions just drawn
    (:func:`_cosine_ratio`; at glossy vertices p / p_bsdf). A contribution c of the path is
    Cycles' c' = c x Π ratio, and the estimate c · s(c'), s Cycles' clamp factor, has the mean of
    Cycles' clamped value E_Cycles[s(c') c'] (importance sampling: c / c' = p_Cycles / p)."""
    weights[idx] *= ratio[:, None]


def _summed(samples):
    """The sum of the light samples of :meth:`IndirectTracer._light_samples`, in their order."""
    total = samples[0]
    for sample in samples[1:]:
        total = total + sample
    return total


def _take(a, index):
    """``a[index]``, or None for None (optional per-path arrays)."""
    return None if a is None else np.take(a, index)


def _even_colour(L, colour):
    """``L (k, 3)`` where the diffuse colour ``colour (k, 3)`` at the start point has zero
    channels, as Cycles' ``safe_divide_even_color`` leaves a pass divided by it: a zero
    channel takes the value of the other channel (two zeros) or the mean of the two others
    (one zero); all three zero give 0."""
    zero = colour <= 0
    some = np.flatnonzero(zero.any(axis=1))
    if len(some) == 0:
        return L
    v, z = L[some].copy(), zero[some]
    v[z] = 0.0
    n = (~z).sum(axis=1, keepdims=True)
    fill = np.where(n > 0, v.sum(axis=1, keepdims=True) / np.maximum(n, 1), 0.0)
    L[some] = np.where(z, fill, v)
    return L


def _add_rows(L, idx, values):
    """``L[idx] += values`` for the distinct rows ``idx`` of the C-contiguous (n, 3) float32
    ``L``: the same sums, with the rows gathered by ``np.take`` and written back as 12-byte
    items (numpy's fancy indexing of (n, 3) rows is several times slower)."""
    total = np.take(L, idx, axis=0)
    total += values
    set_rows(L, idx, total)


def _select_rows(index, *arrays):
    """The rows ``index`` (increasing, as ``np.flatnonzero`` gives them) of every array (the
    live paths of a wavefront); when that is every row, the arrays themselves. An array passed
    twice (flat scenes: the shading normals are the geometric ones) is gathered once and stays
    one array, None stays None."""
    first = next((a for a in arrays if a is not None), None)
    if first is not None and len(index) == len(first):
        return arrays
    return _taken_rows(index, *arrays)


def _taken_rows(index, *arrays):
    """The rows ``index`` (increasing, possibly repeated: the copies of split paths) of every
    array, each distinct array gathered once (as :func:`_select_rows`, without its shortcut: a
    wavefront of as many rows may hold other ones); None stays None."""
    taken = {}
    for a in arrays:
        if a is not None and id(a) not in taken:
            taken[id(a)] = np.take(a, index, axis=0)
    return tuple(None if a is None else taken[id(a)] for a in arrays)


def _channel_max(rgb):
    """Largest of the three channels of (k, 3) values (faster than ``max(axis=1)``)."""
    return np.maximum(np.maximum(rgb[:, 0], rgb[:, 1]), rgb[:, 2])
