"""Surface BSDFs at path vertices as Cycles evaluates them: Diffuse, Principled, Glossy, mixes.

A material is a diffuse lobe (its weight is the triangle's diffuse albedo ρ,
``SceneArrays.triangle_albedo``) plus up to :data:`MAX_LOBES` GGX microfacet reflection lobes
(Walter et al. 2007, Smith masking-shadowing in its non-separable form, Heitz 2014):

* ``DIELECTRIC``: Principled's specular layer. Cycles' generalised Schlick Fresnel with the real
  dielectric curve: ``F = mix(f0, 1, s)``, ``s = (F_d(cos θ_h, η) - F0(η)) / (1 - F0(η))`` with
  ``f0 = F0(η) x Specular Tint`` and η from IOR and Specular IOR Level
  (``F0 = ((η - 1)/(η + 1))² x 2 level``, Principled v2). The diffuse lobe under it is weighted by
  ``1 - max_c(E_F,c(μ))``, the layer's estimated albedo at the view angle μ (Cycles'
  ``closure_layering_weight``);
* ``CONDUCTOR``: Principled's metallic lobe, F82-tint Fresnel (Kutz et al., "Novel aspects of
  the Adobe Standard Material"): ``F = saturate(mix(F0, 1, (1-c)⁵) - B c (1-c)⁶)``;
* ``GLOSSY``: the Glossy BSDF node (no Fresnel, its colour is the lobe's weight).

A lobe's ``multiscatter`` flag is Cycles' "Multiscatter GGX" (the default distribution of the
Principled and Glossy nodes since Blender 4.0): the single-scattering lobe scaled by
``1 + Fms (1 - E(μ)) / E(μ)`` (Turquin 2019, Kulla & Conty 2017), with E the lobe's directional
albedo without Fresnel and Fms the multiple-bounce Fresnel from ``E_avg`` and the lobe's
average Fresnel Fss. The tables E(roughness, μ), E_avg(roughness) and the lobes' average Fresnel
interpolation s(roughness, μ, η) are computed here (:func:`ggx_tables`) on Cycles' grids with
Cycles' definitions (``cycles_precompute.cpp``) and read with Cycles' linear interpolation.

The BSDF of a vertex (:class:`VertexBSDF`) is set up for the direction ωi towards the previous
vertex: per lobe its weight, energy scale and sampling weight (weight x estimated albedo, as
Cycles' ``sample_weight``). :meth:`VertexBSDF.sample` picks a lobe by sampling weight, samples
it (visible-normal sampling, Heitz 2018, for microfacet lobes; cosine for the diffuse one) and
returns ``f cos / p`` with the exact one-sample mixture density ``p = Σ_j w_j p_j / Σ_j w_j``
over all lobes; :meth:`VertexBSDF.eval` gives ``(f cos, p)`` of given directions. Directions
below the geometric surface are absorbed when sampled (Cycles' convention). Roughness at or
below ``α² = 2e-10`` is a mirror: its lobe is sampled as a delta with Cycles' stand-in pdf 1e6
and has no eval.

Arrays: ``normals``, ``wi``, ``wo`` (k, 3) world unit vectors; weights (k, 3) linear RGB.
"""
import functools
from dataclasses import dataclass, field

import numpy as np

INV_PI = 1.0 / np.pi
#: Lobe kinds of :class:`MaterialTable` (0: no lobe).
NONE, DIELECTRIC, CONDUCTOR, GLOSSY = 0, 1, 2, 3
KIND_NAMES = {DIELECTRIC: "dielectric", CONDUCTOR: "conductor", GLOSSY: "glossy"}
#: Most microfacet lobes a material keeps.
MAX_LOBES = 4
#: Cycles' ``roughness_is_almost_specular``: α_x α_y at or below this is a perfect mirror.
SINGULAR_ALPHA2 = 2e-10
#: Cycles' stand-in density of a singular (mirror) lobe, for MIS.
SINGULAR_PDF = 1e6
#: Cycles' ``CLOSURE_WEIGHT_CUTOFF``.
WEIGHT_CUTOFF = 1e-5


# ---- Fresnel ---------------------------------------------------------------------------------------

def fresnel_dielectric(cos_i, eta):
    """Unpolarised Fresnel reflectance of a dielectric interface of relative IOR ``eta`` at
    ``cos θ_i`` (1: total internal reflection), Cycles' ``fresnel_dielectric_cos``."""
    c = np.abs(cos_i)
    g2 = eta * eta - 1.0 + c * c
    g = np.sqrt(np.maximum(g2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (g - c) / (g + c)
        b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
        f = 0.5 * a * a * (1.0 + b * b)
    return np.where(g2 > 0, np.nan_to_num(f, nan=1.0), 1.0)


def f0_from_ior(eta):
    """Normal-incidence reflectance ((η - 1)/(η + 1))²."""
    return ((eta - 1.0) / (eta + 1.0)) ** 2


def ior_from_f0(f0):
    """The IOR whose normal-incidence reflectance is ``f0`` (clamped to 0.99, as Cycles)."""
    s = np.sqrt(np.clip(f0, 0.0, 0.99))
    return (1.0 + s) / (1.0 - s)


def principled_eta_f0(ior, ior_level):
    """``(η, F0)`` of Principled v2's specular layer: ``F0 = F0(IOR) x 2 level`` and the IOR with
    that reflectance (η = IOR at the default level 0.5), as Cycles' ``svm_node_closure_bsdf``."""
    ior = max(float(ior), 1e-5)
    level = max(float(ior_level), 0.0)
    f0 = float(f0_from_ior(ior))
    eta = ior
    if level != 0.5:
        f0 *= 2.0 * level
        eta = float(ior_from_f0(f0))
        if ior < 1.0:
            eta = 1.0 / eta
    return eta, f0


def fresnel_dielectric_fss(eta):
    """Average Fresnel ∫ 2 cos F dcos of a dielectric (Kulla & Conty's fit, Cycles)."""
    eta = np.asarray(eta, dtype=np.float64)
    inside = 0.997118 + eta * (0.1014 - eta * (0.965241 + eta * 0.130607))
    return np.where(eta < 1.0, inside, (eta - 1.0) / (4.08567 + 1.00071 * eta))


def f82_tint_b(f0, tint):
    """The B factor of the F82-tint model: the Schlick value at cos θ = 1/7 times ``tint``."""
    f = 6.0 / 7.0
    f5 = f ** 5
    schlick = f0 + (1.0 - f0) * f5
    return schlick * (7.0 / (f5 * f)) * (1.0 - np.asarray(tint, dtype=np.float64))


def fresnel_f82(cos_i, f0, b):
    """F82-tint Fresnel ``saturate(mix(F0, 1, s⁵) - B cos s⁶)``, s = 1 - cos θ (broadcasts)."""
    s = np.clip(1.0 - cos_i, 0.0, 1.0)
    s5 = s ** 5
    return np.clip(f0 + (1.0 - f0) * s5 - b * cos_i * s5 * s, 0.0, 1.0)


# ---- GGX ------------------------------------------------------------------------------------------

def ggx_d(alpha2, cos_nh):
    """GGX normal distribution D(h) for ``α²``."""
    c2 = cos_nh * cos_nh
    with np.errstate(divide="ignore", invalid="ignore"):   # α = 0: a mirror, never evaluated
        return alpha2 / (np.pi * (1.0 + (alpha2 - 1.0) * c2) ** 2)


def ggx_lambda(alpha2, cos_n):
    """Smith Λ of GGX at ``cos θ`` (Heitz 2014, eq. 72)."""
    c2 = np.maximum(cos_n * cos_n, 1e-300)
    return 0.5 * (np.sqrt(1.0 + alpha2 * np.maximum(1.0 / c2 - 1.0, 0.0)) - 1.0)


def sample_vndf(wi, alpha, u):
    """Visible GGX normals (k, 3) in the local frame (z = normal) for local view directions
    ``wi (k, 3)``, roughness ``alpha (k,)`` and uniforms ``u (k, 2)`` (Heitz 2018, as Cycles'
    ``microfacet_ggx_sample_vndf``)."""
    a = alpha[:, None]
    v = wi * np.concatenate([a, a, np.ones_like(a)], axis=1)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    lensq = v[:, 0] ** 2 + v[:, 1] ** 2
    tilted = lensq > 1e-7
    inv = np.where(tilted, 1.0 / np.sqrt(np.where(tilted, lensq, 1.0)), 0.0)
    t1 = np.where(tilted[:, None], np.stack([-v[:, 1] * inv, v[:, 0] * inv, np.zeros_like(inv)], 1),
                  np.array([1.0, 0.0, 0.0]))
    t2 = np.cross(v, t1)
    r = np.sqrt(u[:, 0])
    phi = 2.0 * np.pi * u[:, 1]
    tx, ty = r * np.cos(phi), r * np.sin(phi)
    s = 0.5 * (1.0 + v[:, 2])
    ty = (1.0 - s) * np.sqrt(np.maximum(1.0 - tx * tx, 0.0)) + s * ty
    tz = np.sqrt(np.maximum(1.0 - tx * tx - ty * ty, 0.0))
    h = tx[:, None] * t1 + ty[:, None] * t2 + tz[:, None] * v
    h = h * np.concatenate([a, a, np.ones_like(a)], axis=1)
    h[:, 2] = np.maximum(h[:, 2], 0.0)
    return h / np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-300)


# ---- Cycles' precomputed tables, recomputed ------------------------------------------------------

def _grid(n):
    return np.clip(np.arange(n) / (n - 1.0), 1e-4, 1.0)


def _ggx_reflect(rough, mu, n):
    """For every (rough, mu) pair (broadcast, flattened to m) an n x n stratified set of VNDF
    samples: ``(cos θ_h·i (m, s), valid (m, s), E weight (m, s))`` with the E weight
    ``(1 + Λ_i)/(1 + Λ_i + Λ_o)`` = eval/pdf of the single-scattering lobe without Fresnel."""
    rough, mu = np.broadcast_arrays(np.asarray(rough, float), np.asarray(mu, float))
    rough, mu = rough.ravel(), mu.ravel()
    m = len(rough)
    j = (np.arange(n) + 0.5) / n
    uu, vv = np.meshgrid(j, j, indexing="ij")
    u = np.stack([uu.ravel(), vv.ravel()], 1)
    s = len(u)
    alpha = np.repeat(rough * rough, s)
    wi = np.stack([np.sqrt(1.0 - mu * mu), np.zeros(m), mu], 1)
    wi_r = np.repeat(wi, s, axis=0)
    h = sample_vndf(wi_r, alpha, np.tile(u, (m, 1)))
    cos_hi = np.sum(h * wi_r, axis=1)
    wo_z = 2.0 * cos_hi * h[:, 2] - wi_r[:, 2]
    valid = wo_z > 0
    a2 = alpha * alpha
    li, lo = ggx_lambda(a2, wi_r[:, 2]), ggx_lambda(a2, np.maximum(wo_z, 1e-12))
    weight = np.where(valid, (1.0 + li) / (1.0 + li + lo), 0.0)
    return cos_hi.reshape(m, s), valid.reshape(m, s), weight.reshape(m, s)


@functools.lru_cache(maxsize=None)
def ggx_tables(n=24):
    """Cycles' GGX tables (``scene/shader.tables``), recomputed with Cycles' definitions on its
    grids (roughness = √α and μ = cos θ_i from 0 to 1, clamped to 1e-4), each entry the mean of
    n² stratified visible-normal samples: ``E (32 μ, 32 rough)`` the directional albedo,
    ``E_avg (32,)`` = ∫ 2μ E dμ, ``s_ior (16 z, 16 μ, 16 rough)`` the mean interpolation factor
    of the real-Fresnel Schlick model for η = ior_from_f0(z⁴), ``s_schlick (2, 16, 16)`` that of
    the exponent model at the two z slices Cycles interpolates at z = 0.5 (exponents 5(1-z)/z for
    z = 7/15 and 8/15). Computed once per process (under a second). Against Cycles' own tables:
    E within 4e-3, E_avg within 1.5e-2 (it only enters the multiple-bounce Fresnel Fms)."""
    r32, m32 = _grid(32), _grid(32)
    rr, mm = np.meshgrid(r32, m32)                         # (mu, rough)
    _, _, w = _ggx_reflect(rr, mm, n)
    E = w.mean(axis=1).reshape(32, 32)
    mu_mid = (np.arange(48) + 0.5) / 48
    rr, mm = np.meshgrid(r32, mu_mid)
    _, _, w = _ggx_reflect(rr, mm, max(2 * n // 3, 8))   # E_avg only scales Fms: coarser
    e_mid = w.mean(axis=1).reshape(48, 32)
    E_avg = np.clip((2.0 * mu_mid[:, None] * e_mid).mean(axis=0), 0.0, 1.0)
    r16, m16 = _grid(16), _grid(16)
    rr, mm = np.meshgrid(r16, m16)
    cos_hi, valid, _ = _ggx_reflect(rr, mm, n)
    z16 = np.clip(np.arange(16) / 15.0, 1e-4, 0.99)
    s_ior = np.empty((16, 16, 16))
    for zi, z in enumerate(z16):                            # 16 slices, vectorised inside
        eta = float(ior_from_f0(z ** 4))
        f0 = float(f0_from_ior(eta))
        s = np.clip((fresnel_dielectric(cos_hi, eta) - f0) / (1.0 - f0), 0.0, 1.0)
        s_ior[zi] = np.where(valid, s, 0.0).mean(axis=1).reshape(16, 16)
    s_schlick = np.empty((2, 16, 16))
    for k, zi in enumerate((7, 8)):
        z = zi / 15.0
        exponent = 5.0 * (1.0 - z) / z
        s = np.clip(1.0 - cos_hi, 0.0, 1.0) ** exponent
        s_schlick[k] = np.where(valid, s, 0.0).mean(axis=1).reshape(16, 16)
    return {"E": np.clip(E, 0.0, 1.0), "E_avg": E_avg, "s_ior": np.clip(s_ior, 0, 1),
            "s_schlick": np.clip(s_schlick, 0, 1)}


def _lerp_index(x, size):
    x = np.clip(x, 0.0, 1.0) * (size - 1)
    i = np.minimum(x.astype(np.int64), size - 1)
    return i, np.minimum(i + 1, size - 1), x - i


def lookup(table, *coords):
    """Cycles' ``lookup_table_read_{1,2,3}D``: multilinear interpolation of ``table`` whose last
    axis is the first coordinate (x = roughness), the one before it the second (y = μ), ..."""
    coords = [np.asarray(c, dtype=np.float64) for c in coords]
    shape = table.shape[::-1]
    strides = np.cumprod((1,) + shape[:-1])         # of the axes in coordinate order (C layout)
    flat_table = np.ascontiguousarray(table).reshape(-1)
    # per axis: the two flat index offsets of the cell and the two weights (t, 1 - t)
    parts = [(i0 * stride, i1 * stride, t, 1.0 - t)
             for (i0, i1, t), stride in zip((_lerp_index(c, n) for c, n in zip(coords, shape)), strides)]
    out = 0.0
    for corner in range(2 ** len(coords)):     # the 2^d corners of the cell (a loop over corners)
        flat, w = 0, 1.0
        for axis, (i0, i1, t, s) in enumerate(parts):
            hi = (corner >> axis) & 1
            flat = flat + (i1 if hi else i0)
            w = w * (t if hi else s)
        out = out + w * np.take(flat_table, flat)
    return out


# ---- materials --------------------------------------------------------------------------------------

@dataclass
class MaterialTable:
    """The microfacet lobes of the scene's materials (M materials x L = :data:`MAX_LOBES` slots).

    kind          (M, L) int8: NONE, DIELECTRIC, CONDUCTOR or GLOSSY
    weight        (M, L, 3) float64 closure weight (Mix Shader factors, metallic, Glossy colour)
    alpha         (M, L) GGX α = roughness²
    eta           (M, L) relative IOR of DIELECTRIC lobes (1 elsewhere)
    f0            (M, L, 3) DIELECTRIC: F0(η) x tint; CONDUCTOR: base colour
    b             (M, L, 3) CONDUCTOR: the F82-tint B factor
    multiscatter  (M, L) bool: Cycles' Multiscatter GGX (energy compensation)
    layer         (M,) int: the DIELECTRIC lobe whose estimated albedo attenuates the diffuse lobe
                  (Principled's specular layer over its diffuse base), -1: none
    names         M material names (for messages)
    filter_glossy Cycles' Filter Glossy (``blur_glossy``) of the scene the materials come from,
                  0: off (:class:`VertexBSDF` ``blur``)
    """

    kind: np.ndarray
    weight: np.ndarray
    alpha: np.ndarray
    eta: np.ndarray
    f0: np.ndarray
    b: np.ndarray
    multiscatter: np.ndarray
    layer: np.ndarray
    names: list = field(default_factory=list)
    filter_glossy: float = 0.0

    def __post_init__(self):
        m = len(self.layer)
        self.kind = np.asarray(self.kind, dtype=np.int8).reshape(m, -1)
        L = self.kind.shape[1]
        self.weight = np.asarray(self.weight, dtype=np.float64).reshape(m, L, 3)
        self.alpha = np.asarray(self.alpha, dtype=np.float64).reshape(m, L)
        self.eta = np.asarray(self.eta, dtype=np.float64).reshape(m, L)
        self.f0 = np.asarray(self.f0, dtype=np.float64).reshape(m, L, 3)
        self.b = np.asarray(self.b, dtype=np.float64).reshape(m, L, 3)
        self.multiscatter = np.asarray(self.multiscatter, dtype=bool).reshape(m, L)
        self.layer = np.asarray(self.layer, dtype=np.int64).reshape(m)
        self.names = list(self.names) or [f"material {i}" for i in range(m)]

    @property
    def glossy(self):
        """(M,) bool: the material has a microfacet lobe."""
        return np.any(self.kind != NONE, axis=1)

    @classmethod
    def from_lobes(cls, materials, names=None):
        """A table from one list of lobes per material; a lobe is a dict with ``kind``,
        ``weight`` (3,), ``roughness`` (Blender's, α = roughness²), and per kind ``eta`` and
        ``f0`` (DIELECTRIC), ``f0`` and ``f82_tint`` (CONDUCTOR), optional ``multiscatter``
        (default True) and ``layer`` (True on the DIELECTRIC lobe over the diffuse base)."""
        m = len(materials)
        L = MAX_LOBES
        kind = np.zeros((m, L), np.int8)
        weight = np.zeros((m, L, 3))
        alpha = np.zeros((m, L))
        eta = np.ones((m, L))
        f0 = np.zeros((m, L, 3))
        b = np.zeros((m, L, 3))
        ms = np.zeros((m, L), bool)
        layer = np.full(m, -1, np.int64)
        for i, lobes in enumerate(materials):
            for j, lobe in enumerate(lobes[:L]):
                kind[i, j] = lobe["kind"]
                weight[i, j] = np.broadcast_to(np.asarray(lobe["weight"], float), 3)
                r = float(np.clip(lobe.get("roughness", 0.5), 0.0, 1.0))
                alpha[i, j] = r * r
                ms[i, j] = bool(lobe.get("multiscatter", True))
                if lobe["kind"] == DIELECTRIC:
                    eta[i, j] = float(lobe["eta"])
                    f0[i, j] = np.clip(np.broadcast_to(np.asarray(lobe["f0"], float), 3), 0.0, 1.0)
                    if lobe.get("layer", False) and layer[i] < 0:
                        layer[i] = j
                elif lobe["kind"] == CONDUCTOR:
                    f0[i, j] = np.clip(np.broadcast_to(np.asarray(lobe["f0"], float), 3), 0.0, 1.0)
                    tint = np.minimum(np.broadcast_to(np.asarray(lobe.get("f82_tint", 1.0), float), 3), 1.0)
                    b[i, j] = 0.0 if np.all(tint == 1.0) else f82_tint_b(f0[i, j], tint)
        return cls(kind, weight, alpha, eta, f0, b, ms, layer, names or [])

    def hemispherical_albedo(self, n_mu=8, n=24):
        """``(diffuse_scale (M, 3), specular (M, 3))``: the cosine-weighted mean over view angles
        (∫ 2μ a(μ) dμ, Gauss-Legendre in μ) of each material's directional albedo a(μ), split into
        the factor of the diffuse albedo (its layering weight) and the microfacet lobes' own
        albedo, so a triangle of diffuse albedo ρ reflects ρ x diffuse_scale + specular of
        uniform incident light."""
        m = len(self.layer)
        x, w = np.polynomial.legendre.leggauss(n_mu)
        mu, w = 0.5 * (x + 1.0), 0.5 * w
        k = m * n_mu
        material = np.repeat(np.arange(m), n_mu)
        mus = np.tile(mu, m)
        wi = np.stack([np.sqrt(1.0 - mus * mus), np.zeros(k), mus], 1)
        normals = np.tile([0.0, 0.0, 1.0], (k, 1))
        white = VertexBSDF(self, material, np.ones((k, 3)), normals, wi).albedo(n)
        black = VertexBSDF(self, material, np.zeros((k, 3)), normals, wi).albedo(n)
        weight = np.tile(2.0 * mu * w, m)[:, None]
        diffuse = ((white - black) * weight).reshape(m, n_mu, 3).sum(axis=1)
        specular = (black * weight).reshape(m, n_mu, 3).sum(axis=1)
        return diffuse, specular

    @classmethod
    def lambertian(cls, count=1):
        """``count`` materials without microfacet lobes."""
        return cls.from_lobes([[] for _ in range(count)])


def principled_lobes(base, metallic=0.0, roughness=0.5, ior=1.5, ior_level=0.5, tint=(1.0, 1.0, 1.0),
                     transmission=0.0, multiscatter=True, scale=1.0):
    """The microfacet lobes (``MaterialTable.from_lobes`` dicts) of a Principled BSDF (v2) with
    these inputs, weights x ``scale`` (a Mix Shader factor), as Cycles sets up its closures:
    Metallic > 0 a CONDUCTOR lobe (weight Metallic, F0 = Base Color, F82 tint = Specular Tint),
    the specular layer a DIELECTRIC lobe (weight (1 - Metallic)(1 - Transmission), η and F0 from
    IOR and Specular IOR Level, F0 x Specular Tint) unless η = 1. Its diffuse part is
    ``base x (1 - Metallic) x (1 - Transmission)``, the triangle's albedo."""
    base = np.clip(np.broadcast_to(np.asarray(base, float), 3), 0.0, 1.0)
    tint = np.maximum(np.broadcast_to(np.asarray(tint, float), 3), 0.0)
    metallic = float(np.clip(metallic, 0.0, 1.0))
    roughness = float(np.clip(roughness, 0.0, 1.0))
    transmission = float(np.clip(transmission, 0.0, 1.0))
    lobes = []
    if metallic > WEIGHT_CUTOFF:
        lobes.append(dict(kind=CONDUCTOR, weight=scale * metallic, roughness=roughness, f0=base,
                          f82_tint=np.minimum(tint, 1.0), multiscatter=multiscatter))
    eta, f0 = principled_eta_f0(ior, ior_level)
    weight = scale * (1.0 - metallic) * (1.0 - transmission)
    if eta != 1.0 and np.all(np.asarray(weight) > WEIGHT_CUTOFF):
        lobes.append(dict(kind=DIELECTRIC, weight=weight, roughness=roughness, eta=eta, f0=f0 * tint,
                          multiscatter=multiscatter, layer=True))
    return lobes


# ---- the BSDF at path vertices ------------------------------------------------------------------------

def valid_specular_normals(ng, wi, n):
    """Cycles' ``ensure_valid_specular_reflection`` (k, 3): the shading normals ``n`` turned
    towards the geometric ``ng`` just enough that the mirror direction of ``wi`` rises at least
    min(0.9 ng·wi, 0.01) above the geometric surface; unchanged where it already does (flat
    triangles: always)."""
    ng, wi, n = (np.asarray(a, dtype=np.float64) for a in (ng, wi, n))
    iz = np.sum(wi * ng, axis=1)
    r = 2.0 * np.sum(n * wi, axis=1)[:, None] * n - wi
    threshold = np.minimum(0.9 * iz, 0.01)
    bad = np.flatnonzero(np.sum(ng * r, axis=1) < threshold)
    if len(bad) == 0:
        return n
    g, i, m, t, z = ng[bad], wi[bad], n[bad], threshold[bad], iz[bad]
    x = m - np.sum(m * g, axis=1)[:, None] * g
    length = np.linalg.norm(x, axis=1, keepdims=True)
    x = np.where(length > 1e-12, x / np.maximum(length, 1e-300), m)
    ix = np.sum(i * x, axis=1)
    a = ix * ix + z * z
    b = 2.0 * (a + z * t)
    c = (t + z) ** 2
    root = np.sqrt(np.maximum(b * b - 4.0 * a * c, 0.0))
    nz2 = np.where(ix < 0, 0.25 * (b + root) / a, 0.25 * (b - root) / a)
    out = n.copy()
    out[bad] = np.sqrt(np.maximum(1.0 - nz2, 0.0))[:, None] * x + np.sqrt(np.maximum(nz2, 0.0))[:, None] * g
    return out


def _frames(n):
    """Tangent frames (t, b) (k, 3) about unit ``n`` (Duff et al. 2017)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], 1)
    s = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], 1)
    return t, s


class VertexBSDF:
    """The BSDF of k path vertices set up for their view directions (module docstring).

    table     :class:`MaterialTable`
    material  (k,) material index of each vertex
    albedo    (k, 3) the diffuse lobe's weight before layering (``triangle_albedo``)
    normals   (k, 3) shading normals N; ``geometric`` (k, 3) Ng of the same side (None: N)
    wi        (k, 3) unit directions towards the previous vertex
    blur      (k,) or None: Cycles' Filter Glossy roughening, α ≥ blur on every lobe after the
              setup (weights, energy compensation and layering keep the material's α, as in
              Cycles' ``bsdf_microfacet_blur``)
    """

    def __init__(self, table, material, albedo, normals, wi, geometric=None, blur=None):
        self.n = np.asarray(normals, dtype=np.float64)
        self.ng = self.n if geometric is None else np.asarray(geometric, dtype=np.float64)
        self.wi = np.asarray(wi, dtype=np.float64)
        k = len(self.n)
        mat = np.asarray(material, dtype=np.int64)
        self.kind = table.kind[mat]                                  # (k, L)
        self.alpha = table.alpha[mat]
        self.eta = table.eta[mat]
        self.f0 = table.f0[mat]
        self.b = table.b[mat]
        #: the microfacet lobes' normal: N lifted so that ωi's mirror direction stays above Ng
        #: (Cycles' ensure_valid_specular_reflection; N on flat triangles)
        self.n_spec = valid_specular_normals(self.ng, self.wi, self.n) if geometric is not None else self.n
        self.mu = np.sum(self.n_spec * self.wi, axis=1)              # (k,) cos θi of the lobes
        mu = np.clip(self.mu, 0.0, 1.0)[:, None]
        rough = np.sqrt(self.alpha)
        tables = ggx_tables()
        active = (self.kind != NONE) & (self.mu[:, None] > 0)
        weight = np.where(active[..., None], table.weight[mat], 0.0)
        active &= np.abs(weight).mean(axis=2) > WEIGHT_CUTOFF
        # estimated albedo of each lobe (Cycles' bsdf_microfacet_estimate_albedo)
        z_ior = np.sqrt(np.abs((self.eta - 1.0) / (self.eta + 1.0)))
        s_ior = lookup(tables["s_ior"], rough, np.broadcast_to(mu, rough.shape), z_ior)
        s_sch = 0.5 * (lookup(tables["s_schlick"][0], rough, np.broadcast_to(mu, rough.shape))
                       + lookup(tables["s_schlick"][1], rough, np.broadcast_to(mu, rough.shape)))
        estimate = np.where((self.kind == DIELECTRIC)[..., None], self.f0 + (1 - self.f0) * s_ior[..., None],
                            np.where((self.kind == CONDUCTOR)[..., None],
                                     self.f0 + (1 - self.f0) * s_sch[..., None], 1.0))
        sample_weight = np.abs(weight).mean(axis=2) * np.where(self.kind == GLOSSY, 1.0, estimate.mean(axis=2))
        # multiscatter energy compensation (Cycles' microfacet_ggx_preserve_energy)
        ms = table.multiscatter[mat] & active
        E = lookup(tables["E"], rough, np.broadcast_to(mu, rough.shape))
        E_avg = lookup(tables["E_avg"], rough)
        missing = np.where(ms, (1.0 - E) / np.maximum(E, 1e-6), 0.0)
        self.energy = 1.0 + missing
        fss_diel = self.f0 + (1 - self.f0) * np.clip(
            (fresnel_dielectric_fss(self.eta) - f0_from_ior(self.eta)) / (1 - f0_from_ior(self.eta)), 0, 1)[..., None]
        fss_cond = self.f0 + (1 - self.f0) / 21.0 - self.b / 126.0
        # Fss: the lobe's average Fresnel; a Glossy node's colour (Cycles' constant Fresnel)
        fss = np.where((self.kind == DIELECTRIC)[..., None], fss_diel,
                       np.where((self.kind == CONDUCTOR)[..., None], fss_cond, weight))
        fms = fss * E_avg[..., None] / (1.0 - fss * (1.0 - E_avg[..., None]))
        darkening = np.where((ms[..., None]) & ~np.isclose(fss, 1.0),
                             (1.0 + fms * missing[..., None]) / self.energy[..., None], 1.0)
        weight = weight * darkening
        sample_weight = sample_weight * np.where(ms, darkening.mean(axis=2), 1.0)
        self.weight = np.where(active[..., None], weight, 0.0)                        # (k, L, 3)
        self.sample_weight = np.where(active, sample_weight, 0.0)                     # (k, L)
        if blur is not None:
            self.alpha = np.maximum(self.alpha, np.asarray(blur, dtype=np.float64)[:, None])
        self.singular = self.alpha * self.alpha <= SINGULAR_ALPHA2
        # the diffuse lobe under the specular layer (Cycles' closure_layering_weight)
        diffuse = np.clip(np.asarray(albedo, dtype=np.float64), 0.0, None).copy()
        lay = table.layer[mat]
        has = np.flatnonzero(lay >= 0)
        if len(has):
            lj = lay[has]
            layer_albedo = darkening[has, lj] * estimate[has, lj]
            cover = np.where(active[has, lj], layer_albedo.max(axis=1), 0.0)
            diffuse[has] *= np.clip(1.0 - cover, 0.0, 1.0)[:, None]
        self.diffuse = diffuse
        self.diffuse_sample_weight = np.abs(diffuse).mean(axis=1)
        self.total_sample_weight = self.diffuse_sample_weight + self.sample_weight.sum(axis=1)
        self.t, self.s = _frames(self.n)
        self.ts, self.ss = _frames(self.n_spec)
        self.k = k

    _ROW_ARRAYS = ("n", "ng", "wi", "kind", "alpha", "eta", "f0", "b", "mu", "energy", "weight",
                   "sample_weight", "singular", "diffuse", "diffuse_sample_weight", "total_sample_weight",
                   "t", "s", "n_spec", "ts", "ss")

    def subset(self, rows):
        """The BSDF of the vertices ``rows`` only (same setup)."""
        out = object.__new__(VertexBSDF)
        for name in self._ROW_ARRAYS:
            setattr(out, name, getattr(self, name)[rows])
        out.k = len(out.n)
        return out

    # ---- lobes ----
    def _fresnel(self, cos_hi, j, rows):
        """F (m, 3) of lobe j at ``cos θ_h·i (m,)`` for the vertices ``rows``."""
        kind = self.kind[rows, j]
        f0 = self.f0[rows, j]
        c = np.clip(cos_hi, 0.0, 1.0)[:, None]
        eta = self.eta[rows, j][:, None]
        f_real = fresnel_dielectric(c, eta)
        f0r = f0_from_ior(eta)
        s = np.clip((f_real - f0r) / np.maximum(1.0 - f0r, 1e-12), 0.0, 1.0)
        diel = f0 + (1.0 - f0) * s
        cond = fresnel_f82(c, f0, self.b[rows, j])
        return np.where((kind == DIELECTRIC)[:, None], diel,
                        np.where((kind == CONDUCTOR)[:, None], cond, 1.0))

    def _lobe_eval(self, wo, j, rows):
        """``(f cos (m, 3), pdf (m,))`` of microfacet lobe j (without its closure weight) for
        directions ``wo (m, 3)`` at the vertices ``rows``."""
        n, wi = self.n_spec[rows], self.wi[rows]
        cos_ni, cos_no = self.mu[rows], np.sum(n * wo, axis=1)
        alpha2 = self.alpha[rows, j] ** 2
        ok = (cos_ni > 0) & (cos_no > 0) & ~self.singular[rows, j] & (self.kind[rows, j] != NONE)
        h = wi + wo
        h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-300)
        cos_hi = np.sum(h * wi, axis=1)
        cos_nh = np.sum(h * n, axis=1)
        D = ggx_d(alpha2, cos_nh)
        li, lo = ggx_lambda(alpha2, cos_ni), ggx_lambda(alpha2, np.maximum(cos_no, 1e-12))
        common = D / np.maximum(cos_ni, 1e-12) * 0.25
        pdf = np.where(ok, common / (1.0 + li), 0.0)
        F = self._fresnel(cos_hi, j, rows)
        f = F * (common / (1.0 + li + lo) * self.energy[rows, j])[:, None]
        return np.where(ok[:, None], f, 0.0), pdf

    # ---- the mixture ----
    def eval(self, wo, rows=None):
        """``(f cos (m, 3), pdf (m,))`` of the whole BSDF for world directions ``wo (m, 3)`` at the
        vertices ``rows`` (default: all): f cos summed over the lobes with their weights, pdf the
        one-sample mixture density Σ_j w_j p_j / Σ_j w_j of :meth:`sample`."""
        rows = np.arange(self.k) if rows is None else np.asarray(rows)
        wo = np.asarray(wo, dtype=np.float64)
        cos_o = np.sum(self.n[rows] * wo, axis=1)
        cos_pdf = np.maximum(cos_o, 0.0) * INV_PI
        f = self.diffuse[rows] * cos_pdf[:, None]
        pdf = self.diffuse_sample_weight[rows] * cos_pdf
        for j in range(self.kind.shape[1]):
            sw = self.sample_weight[rows, j]
            live = np.flatnonzero(sw > 0)
            if len(live) == 0:
                continue
            fj, pj = self._lobe_eval(wo[live], j, rows[live])
            f[live] += self.weight[rows[live], j] * fj
            pdf[live] += sw[live] * pj
        total = self.total_sample_weight[rows]
        return f, np.where(total > 0, pdf / np.where(total > 0, total, 1.0), 0.0)

    def sample(self, u, return_lobe=False):
        """Directions ``wo (k, 3)``, weights ``f cos / p (k, 3)`` and the mixture pdf ``p (k,)``
        from uniforms ``u (k, 3)`` (u[:, 2] picks the lobe by sampling weight, u[:, :2] the
        direction). Absorbed samples (below the geometric or shading surface, or no lobe) have
        weight 0; a mirror lobe's sample gets Cycles' stand-in pdf (1e6 x its selection
        probability) and the weight of its Fresnel alone. ``return_lobe``: also ``(k,)`` int8,
        the kind of lobe sampled: 0 diffuse, 1 microfacet (a glossy bounce, Cycles'
        LABEL_GLOSSY), 2 a mirror (LABEL_SINGULAR)."""
        u = np.asarray(u, dtype=np.float64)
        k = self.k
        total = np.where(self.total_sample_weight > 0, self.total_sample_weight, 1.0)
        cdf = np.cumsum(np.concatenate([self.diffuse_sample_weight[:, None], self.sample_weight], 1), 1) / total[:, None]
        pick = np.minimum(np.sum(u[:, 2:3] >= cdf, axis=1), self.kind.shape[1])  # 0: diffuse, j+1: lobe j
        wo = np.zeros((k, 3))
        # diffuse: cosine-weighted about N
        d = np.flatnonzero(pick == 0)
        if len(d):
            r = np.sqrt(u[d, 0])
            phi = 2.0 * np.pi * u[d, 1]
            x, y, z = r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u[d, 0], 0.0))
            wo[d] = x[:, None] * self.t[d] + y[:, None] * self.s[d] + z[:, None] * self.n[d]
        mirror = np.zeros(k, bool)
        for j in range(self.kind.shape[1]):
            g = np.flatnonzero(pick == j + 1)
            if len(g) == 0:
                continue
            n, t, s, wi = self.n_spec[g], self.ts[g], self.ss[g], self.wi[g]
            sing = self.singular[g, j]
            local = np.stack([np.sum(t * wi, 1), np.sum(s * wi, 1), np.sum(n * wi, 1)], 1)
            h_local = sample_vndf(local, np.maximum(self.alpha[g, j], 1e-6), u[g, :2])
            h = h_local[:, :1] * t + h_local[:, 1:2] * s + h_local[:, 2:3] * n
            h = np.where(sing[:, None], n, h)
            wo[g] = 2.0 * np.sum(h * wi, 1)[:, None] * h - wi
            mirror[g] = sing
        f, pdf = self.eval(wo)
        microfacet = pick > 0
        valid = (np.sum(self.ng * wo, 1) > 0) & (pick <= self.kind.shape[1]) & (self.total_sample_weight > 0)
        valid &= ~microfacet | ((np.sum(self.n_spec * wo, 1) > 0) & (self.mu > 0))
        weight = np.where((pdf > 0)[:, None], f / np.where(pdf > 0, pdf, 1.0)[:, None], 0.0)
        m = np.flatnonzero(mirror & valid)
        if len(m):
            j = pick[m] - 1
            prob = self.sample_weight[m, j] / total[m]
            F = self._mirror_fresnel(m, j)
            weight[m] = self.weight[m, j] * F * self.energy[m, j][:, None] / prob[:, None]
            pdf[m] = SINGULAR_PDF * prob
        weight[~valid] = 0.0
        pdf = np.where(valid, pdf, 0.0)
        if return_lobe:
            return wo, weight, pdf, (microfacet.astype(np.int8) + mirror.astype(np.int8))
        return wo, weight, pdf

    def _mirror_fresnel(self, rows, lobes):
        """F at normal-aligned half vectors (mirror lobes) of the vertices ``rows``, per lobe."""
        out = np.zeros((len(rows), 3))
        for j in np.unique(lobes):
            sel = np.flatnonzero(lobes == j)
            out[sel] = self._fresnel(self.mu[rows[sel]], j, rows[sel])
        return out

    def albedo(self, n=32):
        """Directional albedo (k, 3) ∫ f cos dω: the mean weight of n x n stratified samples of
        :meth:`sample` per vertex (for tests: the white furnace)."""
        j = (np.arange(n) + 0.5) / n
        uu, vv = np.meshgrid(j, j, indexing="ij")
        u = np.stack([uu.ravel(), vv.ravel(), np.mod(uu.ravel() * 7.31 + vv.ravel() * 3.17, 1.0)], 1)
        many = self.subset(np.repeat(np.arange(self.k), n * n))
        _, w, _ = many.sample(np.tile(u, (self.k, 1)))
        return w.reshape(self.k, n * n, 3).mean(axis=1)


class GlossyRows:
    """The glossy vertices among the k vertices of a wavefront, for next-event estimation
    (``lights.EmitterSampler.next_event``): ``mask (k,)`` and their :class:`VertexBSDF`."""

    def __init__(self, k, rows, vertex_bsdf):
        self.mask = np.zeros(k, dtype=bool)
        self.mask[rows] = True
        self.position = np.full(k, -1, dtype=np.int64)
        self.position[rows] = np.arange(len(rows))
        self.bsdf = vertex_bsdf

    def eval_at(self, rows, directions):
        """``(f cos (m, 3), pdf (m,))`` of the BSDF at the wavefront ``rows`` (all glossy)."""
        return self.bsdf.eval(directions, self.position[rows])

    def select(self, index):
        """The same rows after the wavefront keeps only ``index`` (Russian roulette)."""
        keep = np.asarray(index)
        mask = self.mask[keep]
        sub = self.bsdf.subset(self.position[keep[mask]])
        return GlossyRows(len(keep), np.flatnonzero(mask), sub) if len(sub.n) else None


def lambertian_albedo(scene):
    """(T, 3) float32 the albedo the LMDP gives each triangle: ``triangle_albedo`` on Lambertian
    triangles; on glossy ones the hemispherical albedo of the whole BSDF
    (:meth:`MaterialTable.hemispherical_albedo`), i.e. a Lambertian surface that reflects as much
    of uniform incident light (the states keep one unknown per point; the bake samples the
    real BSDF)."""
    albedo = np.clip(np.asarray(scene.triangle_albedo, dtype=np.float64), 0.0, 1.0)
    if not scene.has_glossy():
        return np.asarray(scene.triangle_albedo, dtype=np.float32)
    scale, specular = scene.materials.hemispherical_albedo()
    g = np.flatnonzero(scene.glossy_triangles())
    m = scene.triangle_material[g]
    albedo[g] = np.clip(albedo[g] * scale[m] + specular[m], 0.0, 1.0)
    return albedo.astype(np.float32)


def lambertian_albedo_at(scene, tri, bu, bv):
    """(k, 3) float32 :func:`lambertian_albedo` at points (triangles ``tri``, barycentrics
    ``bu, bv``): the diffuse colour there (``SceneArrays.albedo_at``: textures and colour
    attributes), scaled and raised as in :func:`lambertian_albedo` on glossy triangles."""
    albedo = np.asarray(scene.albedo_at(tri, bu, bv), dtype=np.float32)
    if not scene.has_glossy():
        return albedo
    scale, specular = scene.materials.hemispherical_albedo()
    m = np.asarray(scene.triangle_material)[np.asarray(tri, dtype=np.int64)]
    g = np.flatnonzero(m >= 0)
    out = albedo.astype(np.float64)
    out[g] = np.clip(np.clip(out[g], 0.0, 1.0) * scale[m[g]] + specular[m[g]], 0.0, 1.0)
    return out.astype(np.float32)
