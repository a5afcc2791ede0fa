"""Light connections (lmdp_addon.bake.tracer, ``IndirectTracer(light_share=s)``): with
probability s a path gets a light vertex y' (a point on the emitters, a cosine direction from its
emitting side, the first connectable hit) and every Lambertian eye vertex is joined to y' by a
shadow ray; the light sample at y', the BSDF ray from y' hitting the emitter and the connection
are combined by the balance heuristic. The bake must keep its mean: the tests compare it with
plain path tracing (``light_share=0``) at the same points, within K = 5 standard errors of both
(from the per-path values, many paths per point), on two-sided and one-sided emitters, through
a narrow opening, GUIDED, and under a world; the variance at one bounce must fall (the
feature's purpose); and the bake is deterministic and the feature off where it must be (no
emitter triangles, the sample clamp, FINAL_GATHER, RESIDUAL).
"""
import warnings
from dataclasses import replace

import numpy as np
import pytest

from bake_scenes import K, PATCH_ALBEDO, SKY, small
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import driver as baking
from lmdp_addon.bake.guide import build_guide
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.model import pipeline
from lmdp_addon.raycast import RayCaster
from lmdp_addon.settings import Settings

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def receiver_points(scene, name, n, seed, facing=(0.0, 0.0, 1.0)):
    """``n`` uniform points on the triangles of object ``name`` facing ``facing`` (default up),
    their normals and triangles (``bench/variance_anatomy.py``)."""
    rng = np.random.default_rng(seed)
    obj = scene.object_names.index(name)
    normals, areas = scene.triangle_geometry()
    tri = np.flatnonzero((scene.triangle_object == obj) & (normals @ np.asarray(facing) > 0.5) & (areas > 0))
    pick = tri[rng.choice(len(tri), n, p=areas[tri] / areas[tri].sum())]
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    c = scene.corners()[pick]
    return c[:, 0] + u[:, None] * (c[:, 1] - c[:, 0]) + v[:, None] * (c[:, 2] - c[:, 0]), normals[pick], pick


def path_values(tracer, points, normals, paths, seed, states=None, triangles=None, chunk=1 << 18):
    """(points, paths, 3) float64: each point's per-path estimates (``paths`` paths each), traced
    in wavefronts of at most about ``chunk`` paths (bounded memory), and their TraceStats."""
    k = len(points)
    per = max(1, min(paths, chunk // k))
    out, stats = [], None
    for c, start in enumerate(range(0, paths, per)):
        m = min(per, paths - start)
        rng = np.random.default_rng([seed, c])
        n = k * m
        p, nn = np.repeat(points, m, axis=0), np.repeat(normals, m, axis=0)
        s = np.full(n, -1) if states is None else np.repeat(states, m)
        t = None if triangles is None else np.repeat(triangles, m)
        values, st = tracer.trace(p, nn, s, rng.random((n, 2)), rng.random(n), rng, triangles=t)
        out.append(values.astype(np.float64).reshape(k, m, 3))
        stats = st if stats is None else stats.add(st)
    return np.concatenate(out, axis=1), stats


def mean_and_error(v):
    """Per point and channel (points, 3): the mean and its standard error."""
    return v.mean(axis=1), v.std(axis=1, ddof=1) / np.sqrt(v.shape[1])


def assert_agree(a, b, lit_fraction=0.01):
    """The per-path values ``a`` and ``b`` (points, paths, 3) have the same means: per point and
    channel, and pooled over the points (their mean, far more precise), within K standard errors
    of both. Returns the pooled (mean a, mean b, combined standard error)."""
    (ma, sa), (mb, sb) = mean_and_error(a), mean_and_error(b)
    bound = K * np.sqrt(sa ** 2 + sb ** 2)
    assert np.all(np.abs(ma - mb) <= bound), (ma, mb, bound)
    pa, pb = ma.mean(axis=0), mb.mean(axis=0)
    ps = np.sqrt((sa ** 2 + sb ** 2).sum(axis=0)) / len(ma)
    assert np.all(pb > lit_fraction * pa.max()) and np.all(ps < 0.05 * pa), (pa, ps)   # resolved and lit
    assert np.all(np.abs(pa - pb) <= K * ps), (pa, pb, ps)
    return pa, pb, ps


def relative_variance(v):
    """The luminance's variance per path over its squared mean, averaged over the points."""
    lum = v @ LUMINANCE
    return float((lum.var(axis=1) / lum.mean(axis=1) ** 2).mean())


@pytest.fixture(scope="module")
def cornell_floor(cornell):
    """Six points on the Cornell box's floor that see the room (none under the boxes)."""
    points, normals, tri = receiver_points(cornell, "Floor", 12, seed=0)
    lit = path_values(IndirectTracer(cornell, max_bounces=1), points, normals, 500, seed=0)[0].max(axis=(1, 2)) > 0
    keep = np.flatnonzero(lit)[:6]
    return points[keep], normals[keep], tri[keep], RayCaster(cornell)


@pytest.mark.parametrize("bounces", [1, 8])
@pytest.mark.parametrize("share", [1.0, 0.5])
def test_connections_keep_the_mean_of_path_tracing_on_the_cornell_floor(cornell, cornell_floor, bounces, share):
    """Six floor points, 40 000 paths each, with and without connections: the same means; the
    variance per path falls (at one bounce, where all the light reaches the floor through one
    diffuse vertex, below half of plain path tracing's; at eight below 0.8 of it)."""
    points, normals, tri, caster = cornell_floor
    paths = 40_000
    plain = path_values(IndirectTracer(cornell, max_bounces=bounces, caster=caster), points, normals, paths,
                        seed=10 + bounces, triangles=tri)[0]
    tracer = IndirectTracer(cornell, max_bounces=bounces, caster=caster, light_share=share)
    assert tracer.light_share == share
    joined, stats = path_values(tracer, points, normals, paths, seed=20 + bounces, triangles=tri)
    assert_agree(plain, joined)
    rv_plain, rv_joined = relative_variance(plain), relative_variance(joined)
    assert rv_joined < (0.5 if bounces == 1 else 0.8) * rv_plain, (rv_plain, rv_joined)


def lamp_under_ceiling(gap=0.02, two_sided=False, world=(0.0, 0.0, 0.0), floor=(0.5, 0.5, 0.5)):
    """A 2 m floor (albedo ``floor``, the receiver), a 1 m ceiling patch 1 m above it (albedo
    ``PATCH_ALBEDO``) and a 0.2 m lamp (radiance 10) ``gap`` below the ceiling, facing it: a
    one-sided emitter (an area light, lit side up: every path's light reaches the floor through
    the ceiling, most of it from the bright spot in the gap, which the floor sees around the
    lamp) or a two-sided one (mesh emission, the floor lit directly too), in a world of uniform
    radiance ``world``. Close to the ceiling the light is sampled in its solid angle."""
    e, lx, f = 0.5, 0.1, 1.0
    z = 1.0 - gap
    lamp = scenes._quad_part("Lamp", [(-lx, -lx, z), (lx, -lx, z), (lx, lx, z), (-lx, lx, z)], emission=(10.0,) * 3)
    parts = [scenes._quad_part("Floor", [(-f, -f, 0), (f, -f, 0), (f, f, 0), (-f, f, 0)], floor),
             scenes._quad_part("Ceiling", [(-e, -e, 1), (-e, e, 1), (e, e, 1), (e, -e, 1)], PATCH_ALBEDO),
             replace(lamp, two_sided_emission=two_sided)]
    return scenes.parts_to_scene_arrays(parts, world=world)


FLOOR_POINTS = np.array([(0.15, 0.0, 0.0), (0.3, 0.1, 0.0), (0.5, -0.2, 0.0), (0.05, 0.4, 0.0), (-0.3, -0.3, 0.0),
                         (0.8, 0.6, 0.0)])
UP = np.tile([0.0, 0.0, 1.0], (len(FLOOR_POINTS), 1))


@pytest.mark.parametrize("bounces", [1, 4])
def test_one_sided_lamp_close_to_the_ceiling(bounces):
    """The one-sided lamp 2 cm below the ceiling, lit side up (p_side = 1, the light in the gap
    sampled in its solid angle, where light sampling, the BSDF rays and the connections all
    weigh): six floor points, 300 000 plain paths each (the gap makes them heavy-tailed: variance
    per path / mean² ~ 290) against 40 000 with s = 1 and with s = 0.5 (~ 4.6 and ~ 9.6)."""
    scene = lamp_under_ceiling()
    assert not scene.triangle_emission_two_sided[scene.is_emissive()].any()
    caster = RayCaster(scene)
    plain = path_values(IndirectTracer(scene, max_bounces=bounces, caster=caster), FLOOR_POINTS, UP, 300_000,
                        seed=30 + bounces)[0]
    rv_plain = relative_variance(plain)
    for share, seed in ((1.0, 40), (0.5, 50)):
        joined = path_values(IndirectTracer(scene, max_bounces=bounces, caster=caster, light_share=share),
                             FLOOR_POINTS, UP, 40_000, seed=seed + bounces)[0]
        assert_agree(plain, joined)
        assert relative_variance(joined) < 0.1 * rv_plain, (rv_plain, relative_variance(joined))


def test_two_sided_lamp_under_a_uniform_world():
    """The two-sided lamp 5 cm below the ceiling patch in a uniform world (SKY): the floor's
    indirect light is the patch's reflection of the world and of both sides of the lamp and the
    floor's own light bounced back (4 bounces); connections (s = 1, s = 0.5) keep its mean."""
    scene = lamp_under_ceiling(gap=0.05, two_sided=True, world=(SKY,) * 3)
    caster = RayCaster(scene)
    plain = path_values(IndirectTracer(scene, max_bounces=4, caster=caster), FLOOR_POINTS, UP, 100_000, seed=60)[0]
    for share, seed in ((1.0, 61), (0.5, 62)):
        joined = path_values(IndirectTracer(scene, max_bounces=4, caster=caster, light_share=share),
                             FLOOR_POINTS, UP, 40_000, seed=seed)[0]
        assert_agree(plain, joined)


def lamp_in_a_slot(width=0.05, two_sided=False):
    """A 0.2 m lamp standing on a floor (albedo 0.5, the receiver) facing a wall ``width`` away
    (albedo (0.8, 0.6, 0.4)), one-sided by default: floor points in the slot see the wall close
    by, lit by the lamp close by, where the three strategies all weigh (the eye vertex's density
    of y' per unit area, px (p_L + q) and s P_lt are of the same order), so that a term left out
    of any weight shows."""
    a, h = 0.1, 0.2
    lamp = scenes._quad_part("Lamp", [(0, -a, 0), (0, a, 0), (0, a, h), (0, -a, h)], emission=(10.0,) * 3)
    parts = [scenes._quad_part("Floor", [(-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0)], (0.5,) * 3),
             scenes._quad_part("Wall", [(width, -0.5, 0), (width, -0.5, 0.5), (width, 0.5, 0.5), (width, 0.5, 0)],
                               (0.8, 0.6, 0.4)),
             replace(lamp, two_sided_emission=two_sided)]
    return scenes.parts_to_scene_arrays(parts)


SLOT_POINTS = np.array([(0.01, 0.0, 0.0), (0.025, 0.05, 0.0), (0.04, -0.08, 0.0), (0.02, 0.15, 0.0)])


@pytest.mark.parametrize("two_sided", [False, True])
def test_lamp_facing_a_wall_close_by(two_sided):
    """Four floor points in the slot between the lamp and the wall, 4 bounces: 100 000 plain
    paths each against 40 000 with s = 1 and with s = 0.5, and GUIDED with s = 1 (the fine guide
    of a 512-point solve, which sends the floor's rays to the wall: the eye vertices' density of
    y' is the guide mixture's); the means agree to ~0.3 %."""
    scene = lamp_in_a_slot(two_sided=two_sided)
    lmdp = pipeline.run_all(scene, Settings(point_count=512))
    guide = build_guide(scene, lmdp, fine=True)
    states = guide.states_at(SLOT_POINTS, UP[:len(SLOT_POINTS)], np.zeros(len(SLOT_POINTS), np.int64))
    assert np.all(states >= 0)
    caster = lmdp.dynamics.caster
    up = UP[:len(SLOT_POINTS)]
    plain = path_values(IndirectTracer(scene, max_bounces=4, caster=caster), SLOT_POINTS, up, 100_000, seed=70)[0]
    for mode, share, seed in (("UNGUIDED", 1.0, 71), ("UNGUIDED", 0.5, 72), ("GUIDED", 1.0, 73)):
        tracer = IndirectTracer(scene, mode, max_bounces=4, caster=caster, light_share=share,
                                guide=guide if mode == "GUIDED" else None)
        joined = path_values(tracer, SLOT_POINTS, up, 40_000, seed=seed, states=states)[0]
        assert_agree(plain, joined)


def test_guided_slot_under_a_uniform_world():
    """The slot in a uniform world (SKY), GUIDED with s = 1: there the fine guide's table of the
    texel vertex (light that has bounced) differs from the later vertices' (with the world's
    escape), and the connections from the texel point must use the first one's density (the
    one its direction is drawn from); 100 000 plain UNGUIDED paths per point against 40 000."""
    scene = replace(lamp_in_a_slot(), world_radiance=np.array([SKY] * 3))
    lmdp = pipeline.run_all(scene, Settings(point_count=512))
    guide = build_guide(scene, lmdp, fine=True)
    assert np.abs(guide.first - guide.later).mean() > 0.5 * guide.first.mean()
    up = UP[:len(SLOT_POINTS)]
    states = guide.states_at(SLOT_POINTS, up, np.zeros(len(SLOT_POINTS), np.int64))
    assert np.all(states >= 0)
    caster = lmdp.dynamics.caster
    plain = path_values(IndirectTracer(scene, max_bounces=4, caster=caster), SLOT_POINTS, up, 100_000, seed=94)[0]
    tracer = IndirectTracer(scene, "GUIDED", max_bounces=4, caster=caster, guide=guide, light_share=1.0)
    joined = path_values(tracer, SLOT_POINTS, up, 40_000, seed=95, states=states)[0]
    assert_agree(plain, joined)


def test_direct_and_indirect_times_the_colour_in_the_slot():
    """Cycles' {'DIRECT', 'INDIRECT', 'COLOR'} content (``BakeContent``): the texel's own light
    sample and the emitters its first ray meets stay two-strategy (no light vertex between), the
    connections add to the indirect part only; the same means as without them."""
    from lmdp_addon.bake.content import BakeContent
    scene = lamp_in_a_slot()
    caster = RayCaster(scene)
    content = BakeContent(direct=True, multiply_color=True)
    up, tri = UP[:len(SLOT_POINTS)], triangles_under(scene, SLOT_POINTS, 0)
    plain = path_values(IndirectTracer(scene, max_bounces=4, caster=caster, content=content), SLOT_POINTS, up,
                        100_000, seed=96, triangles=tri)[0]
    joined = path_values(IndirectTracer(scene, max_bounces=4, caster=caster, content=content, light_share=1.0),
                         SLOT_POINTS, up, 40_000, seed=97, triangles=tri)[0]
    indirect = path_values(IndirectTracer(scene, max_bounces=4, caster=caster, light_share=1.0), SLOT_POINTS, up,
                           20_000, seed=98, triangles=tri)[0]
    assert np.all(plain.mean(axis=1) > 1.5 * 0.5 * indirect.mean(axis=1))       # the direct light is in
    assert_agree(plain, joined)


def with_tilted_normals(scene, tilts):
    """``scene`` with smooth shading: the corner normals of each object ``name`` of ``tilts``
    {name: degrees} its face normal turned by the angle about the z axis (about x for faces
    facing up or down), so that shading and geometric cosines differ on it."""
    face = scene.triangle_geometry()[0]
    corner = np.repeat(face[:, None, :], 3, axis=1).astype(np.float64)
    for name, degrees in tilts.items():
        c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
        mask = scene.triangle_object == scene.object_names.index(name)
        flat = abs(face[mask][0, 2]) > 0.5
        rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) if flat else np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        corner[mask] = corner[mask] @ rot.T
    return replace(scene, corner_normals=corner.astype(np.float32))


def triangles_under(scene, points, obj):
    """The triangle of object index ``obj`` under each of ``points`` (k, 3)."""
    corners = scene.corners()
    out = []
    for p in points:
        for t in np.flatnonzero(scene.triangle_object == obj):
            a, b, c = corners[t]
            uv = np.linalg.lstsq(np.array([b - a, c - a]).T, p - a, rcond=None)[0]
            if uv.min() >= -1e-9 and uv.sum() <= 1 + 1e-9:
                out.append(t)
                break
    return np.array(out)


def slot_cases():
    """The slot's variants: smooth shading normals on the floor (15 degrees) and the wall (20
    degrees: the light vertex's shading over geometric cosine, the texel's shading normal);
    a second, coloured emitter of another power (the light vertex's emitter ∝ power, its p_A);
    a Blender point lamp besides the emitter (the lamps keep their own MIS); an environment map
    (its light samples and escapes keep theirs)."""
    from lmdp_addon.lamps import POINT, Lamps
    smooth = with_tilted_normals(lamp_in_a_slot(), {"Floor": 15.0, "Wall": 20.0})
    assert smooth.has_smooth_normals()
    parts = [scenes._quad_part("Floor", [(-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0)], (0.5,) * 3),
             scenes._quad_part("Wall", [(0.05, -0.5, 0), (0.05, -0.5, 0.5), (0.05, 0.5, 0.5), (0.05, 0.5, 0)],
                               (0.8, 0.6, 0.4)),
             replace(scenes._quad_part("Lamp", [(0, -0.1, 0), (0, 0.1, 0), (0, 0.1, 0.2), (0, -0.1, 0.2)],
                                       emission=(10.0,) * 3), two_sided_emission=False),
             scenes._quad_part("Lamp2", [(-0.3, 0.2, 0.3), (-0.3, 0.4, 0.3), (-0.1, 0.4, 0.3), (-0.1, 0.2, 0.3)],
                               emission=(1.0, 2.0, 4.0))]
    two = scenes.parts_to_scene_arrays(parts)
    bulb = lamp_in_a_slot()
    bulb.lamps = Lamps(names=["Bulb"], kind=[POINT], position=[[0.025, 0.0, 0.3]], strength=[[3.0] * 3])
    from test_world import with_environment
    sky = np.full((32, 64, 3), 1.0, np.float32)
    sky[:16, :32] = 4.0                                    # an uneven environment map all round
    environment = with_environment(lamp_in_a_slot(), sky)
    return {"smooth normals": smooth, "two emitters": two, "emitter and lamp": bulb, "environment map": environment}


@pytest.mark.parametrize("case", ["smooth normals", "two emitters", "emitter and lamp", "environment map"])
def test_lamp_facing_a_wall_variants(case):
    """:func:`test_lamp_facing_a_wall_close_by` (UNGUIDED, s = 1 and 0.5) on the variants of
    :func:`slot_cases` (the texels' triangles given, for their shading normals)."""
    scene = slot_cases()[case]
    caster = RayCaster(scene)
    up, tri = UP[:len(SLOT_POINTS)], triangles_under(scene, SLOT_POINTS, 0)
    plain = path_values(IndirectTracer(scene, max_bounces=4, caster=caster), SLOT_POINTS, up, 100_000, seed=75,
                        triangles=tri)[0]
    for share, seed in ((1.0, 76), (0.5, 77)):
        joined = path_values(IndirectTracer(scene, max_bounces=4, caster=caster, light_share=share),
                             SLOT_POINTS, up, 40_000, seed=seed, triangles=tri)[0]
        assert_agree(plain, joined)


def test_glossy_box_connections_skip_the_glossy_vertices():
    """GLOSSY_BOX (a glossy floor, a metallic sphere; the texels' own vertex is Lambertian):
    connections only from Lambertian vertices to Lambertian light vertices, within Cycles'
    diffuse / glossy limits; six floor points, 8 bounces, the same means as plain path tracing,
    and no numpy warnings (rows that are not joined must not divide inf by inf)."""
    scene = scenes.build_scene_arrays("GLOSSY_BOX")
    points, normals, tri = receiver_points(scene, "Floor", 6, seed=2)
    caster = RayCaster(scene)
    plain = path_values(IndirectTracer(scene, max_bounces=8, caster=caster), points, normals, 60_000, seed=90,
                        triangles=tri)[0]
    tracer = IndirectTracer(scene, max_bounces=8, caster=caster, light_share=1.0, glossy_bounces=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        joined, stats = path_values(tracer, points, normals, 30_000, seed=91, triangles=tri)
    assert stats.glossy_vertices > 0
    assert_agree(plain, joined)


def test_glossy_wall_in_the_slot():
    """The slot's wall made a rough metal (Principled, metallic 1, roughness 0.3; no diffuse
    part): the floor's light comes through glossy vertices, which are neither joined to light
    vertices nor light vertices themselves (2 bounces); 200 000 paths per point with and without
    connections (s = 1, light vertices only on the floor): the same means within 5 standard
    errors (~0.35 %), without numpy warnings."""
    a, h, width = 0.1, 0.2, 0.05
    wall = scenes._quad_part("Wall", [(width, -0.5, 0), (width, -0.5, 0.5), (width, 0.5, 0.5), (width, 0.5, 0)],
                             (0.8, 0.6, 0.4))
    parts = [scenes._quad_part("Floor", [(-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0)], (0.5,) * 3),
             replace(wall, principled=dict(roughness=0.3, metallic=1.0)),
             replace(scenes._quad_part("Lamp", [(0, -a, 0), (0, a, 0), (0, a, h), (0, -a, h)], emission=(10.0,) * 3),
                     two_sided_emission=False)]
    scene = scenes.parts_to_scene_arrays(parts)
    assert scene.has_glossy() and np.all(scene.glossy_triangles() == (scene.triangle_object == 1))
    caster = RayCaster(scene)
    up, tri = UP[:len(SLOT_POINTS)], triangles_under(scene, SLOT_POINTS, 0)
    plain = path_values(IndirectTracer(scene, max_bounces=2, caster=caster), SLOT_POINTS, up, 200_000, seed=92,
                        triangles=tri)[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        joined, stats = path_values(IndirectTracer(scene, max_bounces=2, caster=caster, light_share=1.0),
                                    SLOT_POINTS, up, 200_000, seed=93, triangles=tri)
    assert stats.glossy_vertices > 0
    assert_agree(plain, joined)


@pytest.fixture(scope="module")
def narrow():
    scene = scenes.build_scene_arrays("NARROW_OPENING")
    return scene, pipeline.run_all(scene, Settings(point_count=512))


def test_connections_through_the_narrow_opening_unguided_and_guided(narrow):
    """RoomA of the narrow opening is lit only through the hatch (8 bounces): six floor points,
    100 000 plain UNGUIDED paths each against 40 000 UNGUIDED with s = 1 and GUIDED (the fine
    guide; the eye vertices' density of y' is the guide mixture's) with s = 1 and s = 0.5."""
    scene, lmdp = narrow
    guide = build_guide(scene, lmdp, fine=True)
    assert guide.n_strata == 256
    points, normals, tri = receiver_points(scene, "RoomAFloor", 6, seed=1)
    states = guide.states_at(points, normals, np.full(len(points), scene.object_names.index("RoomAFloor")))
    assert np.all(states >= 0)
    caster = lmdp.dynamics.caster
    plain = path_values(IndirectTracer(scene, max_bounces=8, caster=caster), points, normals, 100_000, seed=80,
                        triangles=tri)[0]
    for mode, share, seed in (("UNGUIDED", 1.0, 81), ("GUIDED", 1.0, 82), ("GUIDED", 0.5, 83)):
        tracer = IndirectTracer(scene, mode, max_bounces=8, caster=caster, light_share=share,
                                guide=guide if mode == "GUIDED" else None)
        assert tracer.light_share == share
        joined, stats = path_values(tracer, points, normals, 40_000, seed=seed, states=states, triangles=tri)
        assert_agree(plain, joined)
        assert mode == "UNGUIDED" or stats.guided_vertices > 0


def test_no_connections_without_bounces(cornell, cornell_floor):
    """``max_bounces`` = 0 (Cycles' Diffuse bounces 0; ``driver.bake`` refuses it, the tracer
    takes it): no vertex after the texel point, so no indirect light, with connections too (the
    texel point's light vertex y' would be y_1, beyond the limit); with DIRECT content only the
    direct light, the same bytes as without connections."""
    from lmdp_addon.bake.content import BakeContent
    points, normals, tri, caster = cornell_floor
    for content in (BakeContent(), BakeContent(direct=True)):
        plain = path_values(IndirectTracer(cornell, max_bounces=0, caster=caster, content=content), points, normals,
                            2000, seed=99, triangles=tri)[0]
        joined = path_values(IndirectTracer(cornell, max_bounces=0, caster=caster, content=content, light_share=1.0),
                             points, normals, 2000, seed=99, triangles=tri)[0]
        assert content.direct or np.all(plain == 0)
        np.testing.assert_array_equal(joined, plain)


# ---- through the driver: determinism, and where the connections are off ---------------------------

def baked(scene, settings, lmdp=None, names=("Floor",), threads=None):
    result = baking.bake(scene, list(names), settings, lmdp, threads=threads)
    return np.concatenate([o.image.ravel() for o in result.objects])


def test_driver_bake_with_connections_is_deterministic_whatever_the_threads(cornell, cornell_solved, monkeypatch):
    """``driver.bake`` with light_share 0.5 (UNGUIDED and GUIDED), many units out of order: the
    same seed gives the same bytes with 1 and 2 threads, another seed other bytes, and the
    connections change the bake (they are on)."""
    monkeypatch.setattr(baking, "PATHS_PER_UNIT", 96)
    for mode, lmdp in (("UNGUIDED", None), ("GUIDED", cornell_solved)):
        settings = small(bake_mode=mode, light_share=0.5, seed=3)
        tracer = baking.make_tracer(cornell, settings, lmdp)[0]
        assert tracer.light_share == 0.5
        a, b = baked(cornell, settings, lmdp, threads=1), baked(cornell, settings, lmdp, threads=2)
        np.testing.assert_array_equal(a, b)
        assert not np.array_equal(a, baked(cornell, replace(settings, seed=4), lmdp, threads=2))
        assert not np.array_equal(a, baked(cornell, replace(settings, light_share=0.0), lmdp, threads=2))


def test_no_connections_without_emitter_triangles():
    """PLANE_UNDER_SKY has no emitter triangles (only the world), the lamp room of ``test_lamps``
    only Blender lamps: light_share 0.5 bakes the same bytes as 0 (no light vertices, no random
    numbers drawn for them)."""
    from test_lamps import lamp_room
    for scene, name in ((scenes.build_scene_arrays("PLANE_UNDER_SKY"), "Plane"), (lamp_room(), "Floor")):
        settings = small(light_share=0.5, seed=2)
        assert baking.make_tracer(scene, settings)[0].light_share == 0.0
        image = baked(scene, settings, names=(name,))
        assert image.max() > 0
        np.testing.assert_array_equal(image, baked(scene, replace(settings, light_share=0.0), names=(name,)))


@pytest.mark.parametrize("case", ["clamp_indirect", "clamp_direct", "FINAL_GATHER", "RESIDUAL", "transparency"])
def test_light_share_is_ignored_with_the_clamp_transparency_and_in_gather_modes(cornell, cornell_solved, case):
    """With Cycles' sample clamp (either limit), with transparent surfaces (a leaf of alpha 0.5
    in the Cornell box, ``test_textures``) and in FINAL_GATHER and RESIDUAL bakes the
    connections are off: light_share 0.5 bakes the same bytes as 0."""
    if case == "transparency":
        from test_textures import cornell_with_leaf
        cornell, settings, lmdp = cornell_with_leaf(0.5), small(light_share=0.5, seed=5), None
    elif case.startswith("clamp"):
        settings, lmdp = small(light_share=0.5, seed=5, **{case: 1.0}), None
    else:
        settings, lmdp = small(bake_mode=case, light_share=0.5, seed=5), cornell_solved
    assert baking.make_tracer(cornell, settings, lmdp)[0].light_share == 0.0
    np.testing.assert_array_equal(baked(cornell, settings, lmdp), baked(cornell, replace(settings, light_share=0.0), lmdp))
