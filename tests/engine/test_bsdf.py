"""The BSDFs at path vertices (lmdp_addon/bsdf.py): exact densities, consistent weights, energy.

* the mixture pdf integrates over the sphere to the probability that a sample is kept (1 for
  the diffuse lobe; microfacet samples reflected below the surface are absorbed);
* ``sample`` returns ``f cos / p`` with exactly the ``eval`` of the same direction;
* white furnace: a white Multiscatter GGX Glossy lobe reflects all the light for every view
  angle and roughness (Cycles' energy compensation), a single-scatter one reflects Cycles' own
  tabulated directional albedo ``table_ggx_E`` (``scene/shader.tables``), which our
  recomputed table matches;
* Fresnel: Principled's default specular layer (IOR 1.5, level 0.5) reflects F0 = 4 % at
  normal incidence on a mirror, level 0 switches it off, F82 tint 1 is Schlick's curve.
"""
import numpy as np
import pytest

from lmdp_addon import bsdf

#: Cycles' table_ggx_E (scene/shader.tables, 32 x 32, rows μ = y/31, columns roughness = x/31):
#: rows 1 and 5, columns 0..7 and 27..31.
CYCLES_E = {
    1: ([1.000000, 0.999451, 0.990086, 0.954714, 0.911203, 0.891678, 0.893893, 0.905010],
        [0.911810, 0.906184, 0.900361, 0.894361, 0.888202]),
    5: ([1.000000, 0.999979, 0.999644, 0.998096, 0.993618, 0.983950, 0.967765, 0.946488],
        [0.745308, 0.729926, 0.714121, 0.697985, 0.681600]),
}


def one_vertex(lobes, albedo=(0.0, 0.0, 0.0), mu=0.6, k=1):
    table = bsdf.MaterialTable.from_lobes([lobes])
    wi = np.tile([np.sqrt(1 - mu * mu), 0.0, mu], (k, 1))
    n = np.tile([0.0, 0.0, 1.0], (k, 1))
    return bsdf.VertexBSDF(table, np.zeros(k, int), np.tile(albedo, (k, 1)), n, wi)


def sphere_grid(n):
    """Midpoint quadrature of the sphere: directions (n², 3) and their solid angle each."""
    j = (np.arange(n) + 0.5) / n
    cz, phi = np.meshgrid(2 * j - 1, 2 * np.pi * j, indexing="ij")
    s = np.sqrt(1 - cz ** 2)
    d = np.stack([s * np.cos(phi), s * np.sin(phi), cz], -1).reshape(-1, 3)
    return d, 4 * np.pi / (n * n)


def test_recomputed_albedo_table_matches_cycles():
    E = bsdf.ggx_tables()["E"]
    for row, (first, last) in CYCLES_E.items():
        np.testing.assert_allclose(E[row, :8], first, atol=4e-3)
        np.testing.assert_allclose(E[row, -5:], last, atol=4e-3)


@pytest.mark.parametrize("lobes,albedo", [
    ([], (0.8, 0.8, 0.8)),
    ([dict(kind=bsdf.GLOSSY, weight=1.0, roughness=0.5)], (0, 0, 0)),
    ([dict(kind=bsdf.DIELECTRIC, weight=1.0, roughness=0.6, eta=1.5, f0=0.04, layer=True)], (0.8, 0.5, 0.2)),
    ([dict(kind=bsdf.CONDUCTOR, weight=0.7, roughness=0.7, f0=(0.9, 0.6, 0.3), f82_tint=(0.8, 0.9, 1.0)),
      dict(kind=bsdf.DIELECTRIC, weight=0.3, roughness=0.7, eta=1.5, f0=0.04, layer=True)], (0.24, 0.24, 0.24)),
], ids=["diffuse", "glossy", "principled", "metallic_mix"])
def test_pdf_integrates_to_the_kept_fraction_and_weights_are_eval_over_pdf(lobes, albedo):
    mu = 0.6
    d, dw = sphere_grid(500)
    v = one_vertex(lobes, albedo, mu, k=len(d))
    _, pdf = v.eval(d)
    integral = pdf.sum() * dw
    # the fraction of samples kept, by stratified sampling
    m = 256
    j = (np.arange(m) + 0.5) / m
    uu, vv = np.meshgrid(j, j, indexing="ij")
    u = np.stack([uu.ravel(), vv.ravel(), np.mod(uu.ravel() * 0.618 * m, 1.0)], 1)
    s = one_vertex(lobes, albedo, mu, k=len(u))
    wo, weight, p = s.sample(u)
    kept = np.mean(p > 0)
    assert abs(integral - kept) < 0.01, (integral, kept)
    f, q = s.eval(wo)
    ok = p > 0
    np.testing.assert_allclose(q[ok], p[ok], rtol=1e-9)
    np.testing.assert_allclose(weight[ok], f[ok] / p[ok, None], rtol=1e-9)
    # the albedo by sampling equals the albedo by quadrature of eval
    f_grid, _ = v.eval(d)
    np.testing.assert_allclose(weight.mean(axis=0), f_grid.sum(axis=0) * dw, rtol=0.02, atol=2e-3)


@pytest.mark.parametrize("roughness", [0.2, 0.5, 0.9])
@pytest.mark.parametrize("mu", [0.2, 0.5, 0.95])
def test_white_furnace(roughness, mu):
    """Multiscatter GGX white Glossy: albedo 1 (within the quadrature's error); single-scatter:
    Cycles' directional albedo E(μ, roughness) from its table."""
    multi = one_vertex([dict(kind=bsdf.GLOSSY, weight=1.0, roughness=roughness)], mu=mu)
    single = one_vertex([dict(kind=bsdf.GLOSSY, weight=1.0, roughness=roughness, multiscatter=False)], mu=mu)
    a_multi = multi.albedo(64)[0, 0]
    a_single = single.albedo(64)[0, 0]
    E = bsdf.lookup(bsdf.ggx_tables()["E"], roughness, mu)
    assert abs(a_multi - 1.0) < 0.01, a_multi
    assert abs(a_single - E) < 0.01, (a_single, E)
    assert a_single < 1.0 or roughness < 0.3


def test_principled_fresnel_at_normal_incidence():
    eta, f0 = bsdf.principled_eta_f0(1.5, 0.5)
    assert eta == 1.5 and abs(f0 - 0.04) < 1e-12
    eta0, f00 = bsdf.principled_eta_f0(1.5, 0.0)
    assert f00 == 0.0 and eta0 == 1.0
    eta1, f01 = bsdf.principled_eta_f0(1.5, 1.0)
    assert abs(f01 - 0.08) < 1e-12 and abs(bsdf.f0_from_ior(eta1) - 0.08) < 1e-9
    assert abs(bsdf.fresnel_dielectric(1.0, 1.5) - 0.04) < 1e-12
    # a mirror dielectric reflects F(μ) along the mirror direction, the diffuse lobe under it
    # keeps 1 - F (Cycles' layering); F82 with tint 1 is Schlick's curve
    v = one_vertex([dict(kind=bsdf.DIELECTRIC, weight=1.0, roughness=0.0, eta=1.5, f0=0.04, layer=True)],
                   albedo=(1, 1, 1), mu=1.0)
    assert abs(v.diffuse[0, 0] - (1 - 0.04)) < 2e-3
    c = np.linspace(0, 1, 11)
    np.testing.assert_allclose(bsdf.fresnel_f82(c, 0.5, 0.0), 0.5 + 0.5 * (1 - c) ** 5)


def test_mirror_lobe_reflects_its_fresnel():
    v = one_vertex([dict(kind=bsdf.CONDUCTOR, weight=1.0, roughness=0.0, f0=(0.9, 0.5, 0.2))], mu=0.8, k=4)
    wo, weight, pdf = v.sample(np.full((4, 3), 0.3))
    np.testing.assert_allclose(wo[0], [-0.6, 0.0, 0.8], atol=1e-12)
    expect = bsdf.fresnel_f82(0.8, np.array([0.9, 0.5, 0.2]), 0.0)
    np.testing.assert_allclose(weight[0], expect, rtol=1e-9)
    assert pdf[0] >= bsdf.SINGULAR_PDF * 0.99


#: Cycles' table_ggx_Eavg (scene/shader.tables), every fourth roughness x/31.
CYCLES_E_AVG = [1.000000, 0.998729, 0.985805, 0.946279, 0.870874, 0.761345, 0.631068, 0.499191]


def test_recomputed_average_albedo_matches_cycles():
    np.testing.assert_allclose(bsdf.ggx_tables()["E_avg"][::4], CYCLES_E_AVG, atol=1.5e-2)


def test_hemispherical_albedo_is_the_lmdp_albedo_of_glossy_surfaces():
    """A white Multiscatter Glossy reflects all uniform light (1), a single-scatter one E_avg; a
    white Principled dielectric keeps most of its diffuse albedo and adds its specular albedo,
    about 1 in all; Lambertian scenes keep triangle_albedo exactly, the metal sphere of
    GLOSSY_BOX (diffuse albedo 0) gets its metal's."""
    table = bsdf.MaterialTable.from_lobes([
        [dict(kind=bsdf.GLOSSY, weight=1.0, roughness=0.5)],
        [dict(kind=bsdf.GLOSSY, weight=1.0, roughness=0.5, multiscatter=False)],
        bsdf.principled_lobes((0.8, 0.8, 0.8), roughness=0.5),
    ])
    scale, specular = table.hemispherical_albedo()
    assert abs(specular[0, 0] - 1.0) < 0.01
    assert abs(specular[1, 0] - bsdf.lookup(bsdf.ggx_tables()["E_avg"], 0.5)) < 0.01
    assert 0.85 < scale[2, 0] < 0.96 and 0.04 < specular[2, 0] < 0.15
    assert abs(scale[2, 0] + specular[2, 0] - 1.0) < 0.02       # white: energy conserving
    from lmdp_addon import demo_geometry as scenes
    plain = scenes.build_scene_arrays("CORNELL_BOX")
    assert np.array_equal(bsdf.lambertian_albedo(plain), plain.triangle_albedo)
    glossy = scenes.build_scene_arrays("GLOSSY_BOX")
    a = bsdf.lambertian_albedo(glossy)
    metal = glossy.triangle_object == glossy.object_names.index("MetalSphere")
    assert np.all(a[metal].max(axis=1) > 0.5) and np.all(glossy.triangle_albedo[metal] == 0)


def test_valid_specular_normals_lift_the_mirror_direction():
    """Cycles' ensure_valid_specular_reflection: a shading normal whose mirror direction of ωi
    dips below the geometric surface is turned towards Ng until it rises to min(0.9 ωi·Ng,
    0.01); normals whose reflection is fine (and Ng itself) are kept."""
    ng = np.tile([0.0, 0.0, 1.0], (3, 1))
    n = np.array([[np.sin(0.5), 0.0, np.cos(0.5)], [np.sin(0.1), 0.0, np.cos(0.1)], [0.0, 0.0, 1.0]])
    wi = np.tile([-np.sin(1.3), 0.0, np.cos(1.3)], (3, 1))
    out = bsdf.valid_specular_normals(ng, wi, n)
    r = 2.0 * np.sum(out * wi, axis=1)[:, None] * out - wi
    assert abs(r[0, 2] - min(0.9 * np.cos(1.3), 0.01)) < 1e-9
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0)
    np.testing.assert_array_equal(out[1:], n[1:])
