"""State space (thesis 3.1.1): surface points proportional to area, each with a stratified hemisphere.

A state is the pair (point, stratum). On a Lambertian point every stratum has the same row of
the passive dynamics (eq. 3.1 does not depend on the outgoing direction), so the transport solve
carries one unknown per point; a glossy point (a material with a microfacet lobe) keeps one
unknown per outgoing stratum (:mod:`~lmdp_addon.model.unknowns`, :attr:`StateSpace.unknowns`);
see ``design.md``.
"""
import functools
from dataclasses import dataclass

import numpy as np

from ..bsdf import lambertian_albedo_at
from ..errors import SceneError
from .hemisphere import stratum_cosine_weights, stratum_solid_angle, tangent_frame
from .unknowns import UnknownMap

from ..sampling import GOLDEN


@dataclass
class StateSpace:
    """Points and hemisphere strata that make up the LMDP states.

    points          (m, 3) float64 world metres
    normals         (m, 3) float64 unit geometric normals (the side the states live on)
    frames          (m, 3, 3) float64 tangent frames (rows t, b, n), see hemisphere.tangent_frame
    point_triangle  (m,) int64 triangle each point lies on
    point_object    (m,) int32 object index (SceneArrays.object_names)
    point_albedo    (m, 3) float32 diffuse reflectance at the point (textured; on glossy surfaces the
                    hemispherical albedo of their BSDF, ``bsdf.lambertian_albedo_at``)
    point_area      (m,) float64 surface area each point stands for (m^2)
    strata_u, strata_v  hemisphere grid; S = strata_u * strata_v strata per point
    stratum_weight  (S,) float64 ∫_k cos θ dω / π, the Lambertian mass of each stratum
    skipped_triangles   number of zero-area / non-finite triangles on the selected meshes
    shading_normals (m, 3) float64 unit shading normals at the points (interpolated corner
                    normals, ``SceneArrays.shading_normals``), or None: equal to ``normals``
                    (flat scenes). The strata and their frames stay those of the geometric
                    normal; see :attr:`bsdf_normals`
    glossy          (m,) bool: the point's material has a microfacet lobe (``bsdf.MaterialTable``),
                    so it carries one unknown per outgoing stratum; None: no glossy point
    point_bary      (m, 2) float64 barycentrics (b1, b2) of each point on its triangle (the
                    glossy points' BSDF reads the diffuse colour there), or None
    """

    points: np.ndarray
    normals: np.ndarray
    frames: np.ndarray
    point_triangle: np.ndarray
    point_object: np.ndarray
    point_albedo: np.ndarray
    point_area: np.ndarray
    strata_u: int
    strata_v: int
    stratum_weight: np.ndarray
    skipped_triangles: int = 0
    seed: int = 0
    shading_normals: np.ndarray = None
    glossy: np.ndarray = None
    point_bary: np.ndarray = None

    @functools.cached_property
    def unknowns(self):
        """The :class:`~lmdp_addon.model.unknowns.UnknownMap` of the LMDP's unknowns."""
        glossy = np.zeros(self.n_points, dtype=bool) if self.glossy is None else self.glossy
        return UnknownMap(glossy, self.strata_u, self.strata_v)

    @property
    def n_unknowns(self):
        """Unknowns of the solve: one per Lambertian point, S per glossy point."""
        return self.unknowns.n_unknowns

    @property
    def bsdf_normals(self):
        """(m, 3) the normals the BSDF shades with: :attr:`shading_normals`, else :attr:`normals`."""
        return self.normals if self.shading_normals is None else self.shading_normals

    @property
    def n_points(self):
        return len(self.points)

    @property
    def n_strata(self):
        return self.strata_u * self.strata_v

    @property
    def n_states(self):
        """Number of (point, stratum) states, the thesis's state count."""
        return self.n_points * self.n_strata

    @property
    def stratum_solid_angle(self):
        return stratum_solid_angle(self.strata_u, self.strata_v)

    def summary(self):
        glossy = self.unknowns.n_glossy
        return (f"{self.n_points} points x {self.n_strata} strata = {self.n_states} states"
                + (f"; {glossy} glossy points carry {self.n_strata} directional unknowns each "
                   f"({self.n_unknowns} unknowns)" if glossy else "")
                + (f"; skipped {self.skipped_triangles} degenerate triangles" if self.skipped_triangles else ""))


def sample_states(scene, point_count, strata_u=4, strata_v=4, seed=0):
    """Sample ``point_count`` points on the state-carrying triangles of ``scene`` (thesis 3.1.1).

    Points are distributed proportionally to world-space area and stratified: the i-th point takes
    ``u_i = (i + ξ)/N`` on the cumulative-area line (so every triangle receives its area share to
    within one point), the remainder of ``u_i`` inside its triangle as the first barycentric
    coordinate and the golden-ratio sequence ``frac(i/φ + ξ')`` as the second. Deterministic for
    a given ``seed``.
    """
    point_count = int(point_count)
    if point_count < 1:
        raise SceneError(f"Point count must be at least 1 (got {point_count})")
    if strata_u < 1 or strata_v < 1:
        raise SceneError(f"Strata must be at least 1 x 1 (got {strata_u} x {strata_v})")
    with scene.held():
        return _sample(scene, point_count, int(strata_u), int(strata_v), seed)


def _sample(scene, point_count, strata_u, strata_v, seed):
    """:func:`sample_states` with the scene's derived geometry held."""
    scene.check_for_lmdp()
    normals, areas = scene.triangle_geometry()
    on_selected = scene.object_carries_states[scene.triangle_object] & ~scene.is_emissive()
    skipped = int(np.count_nonzero(on_selected & ~(areas > 0)))
    carriers = np.flatnonzero(scene.state_triangles())
    carrier_area = areas[carriers]
    cdf = np.cumsum(carrier_area)
    total = cdf[-1]

    rng = np.random.default_rng(seed)
    xi, xi2 = rng.random(2)
    i = np.arange(point_count, dtype=np.float64)
    u = (i + xi) / point_count * total
    which = np.minimum(np.searchsorted(cdf, u, side="right"), len(carriers) - 1)
    start = cdf[which] - carrier_area[which]
    r1 = np.clip((u - start) / carrier_area[which], 0.0, 1.0)
    r2 = np.mod(i * GOLDEN + xi2, 1.0)
    tri = carriers[which]

    # Uniform square -> triangle warp (area preserving): b0 = 1 - sqrt(r1), b1 = sqrt(r1)(1 - r2).
    s = np.sqrt(r1)
    bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)
    corners = scene.corners()[tri]
    points = np.einsum("mk,mkj->mj", bary, corners)
    point_normals = normals[tri]
    glossy = None
    if scene.has_glossy():
        glossy = np.asarray(scene.glossy_triangles(), dtype=bool)[tri]
        glossy = glossy if glossy.any() else None
    shading = None
    if scene.has_smooth_normals():
        shading = scene.shading_normals(tri, bary[:, 1], bary[:, 2]).astype(np.float64)

    obj = scene.triangle_object[tri]
    # Each point stands for an equal share of its object's sampled area.
    point_area = np.empty(point_count)
    for o in np.unique(obj):  # loop over objects, not points
        mask = obj == o
        point_area[mask] = areas[carriers][scene.triangle_object[carriers] == o].sum() / mask.sum()

    return StateSpace(
        points=points,
        normals=point_normals,
        frames=tangent_frame(point_normals),
        point_triangle=tri.astype(np.int64),
        point_object=obj.astype(np.int32),
        point_albedo=lambertian_albedo_at(scene, tri, bary[:, 1], bary[:, 2]),   # glossy: the BSDF's hemispherical albedo
        point_area=point_area,
        strata_u=int(strata_u),
        strata_v=int(strata_v),
        stratum_weight=stratum_cosine_weights(int(strata_u), int(strata_v)),
        skipped_triangles=skipped,
        seed=int(seed),
        shading_normals=shading,
        glossy=glossy,
        point_bary=bary[:, 1:].copy(),
    )
