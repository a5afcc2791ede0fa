"""The solved LMDP's Russian roulette and splitting (lmdp_addon.bake.splitting, the tracer's
``splitting=`` and ``_Paths``): a weight window on r = lum(β) V(y_k) / V(s_0) splits paths
whose share of the answer is above one into at most MAX_COPIES copies (β / n each) and plays
roulette with survival max(r, SURVIVAL_FLOOR) below one.

Whatever V is, the estimate must keep the mean of plain path tracing: GUIDED + splitting against
plain UNGUIDED (light_share 0, no splitting) at the same points, within K = 5 standard errors of
both, through the narrow opening (RoomAFloor, lit only through the hatch), on the Cornell floor,
on the glossy box, and with deliberately wrong V (random, inverted). The window keeps its
contract (unknown rows untouched, copies in [1, MAX_COPIES], survival at least the floor, roulette
only where allowed, the expected weight of the copies and survivors the path's); splitting
happens and lowers the variance per path through the hatch; it is off with the sample clamp and
in the gather modes; the bake is byte-identical whatever the threads.
"""
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from bake_scenes import K, small
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import driver as baking
from lmdp_addon.bake import splitting, tracer as tracer_module
from lmdp_addon.bake.clamp import SampleClamp
from lmdp_addon.bake.guide import build_guide
from lmdp_addon.bake.splitting import MAX_COPIES, SURVIVAL_FLOOR, SplitField
from lmdp_addon.bake.tracer import IndirectTracer, _Paths
from lmdp_addon.model import pipeline
from lmdp_addon.settings import Settings
from test_light_connections import mean_and_error, path_values, receiver_points, relative_variance


def agree(a, b, resolved=0.1):
    """The per-path values ``a`` and ``b`` (points, paths, 3) have the same means, per point and
    channel and pooled over the points, within K standard errors of both (combined); the pooled
    estimate is resolved (its standard error below ``resolved`` of the mean). Returns the pooled
    (mean a, mean b, combined standard error)."""
    (ma, sa), (mb, sb) = mean_and_error(a), mean_and_error(b)
    assert np.all(np.abs(ma - mb) <= K * np.sqrt(sa ** 2 + sb ** 2)), (ma, mb, np.sqrt(sa ** 2 + sb ** 2))
    pa, pb = ma.mean(axis=0), mb.mean(axis=0)
    ps = np.sqrt((sa ** 2 + sb ** 2).sum(axis=0)) / len(ma)
    assert np.all(pa > 0) and np.all(ps < resolved * pa), (pa, ps)
    assert np.all(np.abs(pa - pb) <= K * ps), (pa, pb, ps)
    return pa, pb, ps


def inverted(field):
    """``field`` with V turned upside down where it is known (bright where it was dark)."""
    v = field.value
    pos = v > 0
    out = np.zeros_like(v)
    out[pos] = v[pos].max() * v[pos].min() / v[pos]
    return replace(field, value=out)


def randomised(field, seed=0):
    """``field`` with V uniform random in [0, max V] at every state (no relation to the light)."""
    return replace(field, value=np.random.default_rng(seed).random(len(field.value)) * field.value.max())


class Recorder:
    """Wraps ``splitting.window`` (as the tracer calls it) and keeps the copies and survivals."""

    def __init__(self):
        self.copies, self.survival = [], []

    def __call__(self, ratio, known, roulette, rng):
        p, n = splitting.window(ratio, known, roulette, rng)
        self.copies.append(n.copy())
        self.survival.append(p.copy())
        return p, n


# ---- the scenes ----------------------------------------------------------------------------------

def solved_points(kind, receiver, seed):
    """``(scene, lmdp, fine guide, SplitField, points, normals, triangles, states)``: the built-in
    scene ``kind`` solved with 512 points, six points of object ``receiver`` and their states."""
    scene = scenes.build_scene_arrays(kind)
    lmdp = pipeline.run_all(scene, Settings(point_count=512))
    guide = build_guide(scene, lmdp, fine=True)
    points, normals, tri = receiver_points(scene, receiver, 6, seed=seed)
    states = guide.states_at(points, normals, np.full(len(points), scene.object_names.index(receiver)))
    return scene, lmdp, guide, SplitField.from_lmdp(scene, lmdp), points, normals, tri, states


@pytest.fixture(scope="module")
def narrow():
    """The narrow opening solved (512 points), its fine guide, V and six RoomAFloor points with
    their states (each has one, and V is known there)."""
    scene, lmdp, guide, field, points, normals, tri, states = solved_points("NARROW_OPENING", "RoomAFloor", 1)
    assert np.all(states >= 0) and np.all(field.at_states(states) > 0)
    caster = lmdp.dynamics.caster
    plain = path_values(IndirectTracer(scene, max_bounces=8, caster=caster), points, normals, 80_000, seed=100,
                        triangles=tri)[0]
    return SimpleNamespace(scene=scene, lmdp=lmdp, guide=guide, field=field, points=points, normals=normals,
                           tri=tri, states=states, caster=caster, plain=plain)


def guided(case, field, paths, seed, light_share=0.0, **kw):
    """Per-path values and TraceStats of GUIDED (+ ``field``'s splitting) at ``case``'s points."""
    tr = IndirectTracer(case.scene, "GUIDED", max_bounces=8, caster=case.caster, guide=case.guide,
                        splitting=field, light_share=light_share, **kw)
    assert (tr.splitting is None) == (field is None)
    return path_values(tr, case.points, case.normals, paths, seed=seed, states=case.states, triangles=case.tri)


# ---- (a) unbiased --------------------------------------------------------------------------------

@pytest.mark.parametrize("light_share", [0.0, 0.5])
def test_guided_splitting_keeps_the_mean_through_the_narrow_opening(narrow, light_share):
    """Six RoomAFloor points, 80 000 plain UNGUIDED paths each (no connections, no splitting)
    against 30 000 GUIDED + splitting (without and with light connections: the copies share
    their parent's light vertex and balance-heuristic state): the same means within 5 s.e."""
    values, stats = guided(narrow, narrow.field, 30_000, seed=101 + int(light_share * 10), light_share=light_share)
    agree(narrow.plain, values)
    assert stats.guided_vertices > 0
    assert light_share == 0 or stats.connections > 0


def test_guided_splitting_keeps_the_mean_on_the_cornell_floor(cornell, cornell_solved):
    """Six Cornell floor points that see the room: 60 000 plain UNGUIDED paths each against
    30 000 GUIDED + splitting (the window where most of the light is near the start)."""
    points, normals, tri = receiver_points(cornell, "Floor", 12, seed=0)
    guide = build_guide(cornell, cornell_solved, fine=True)
    states = guide.states_at(points, normals, np.full(len(points), cornell.object_names.index("Floor")))
    field = SplitField.from_lmdp(cornell, cornell_solved)
    keep = np.flatnonzero((states >= 0) & (field.at_states(states) > 0))[:6]
    assert len(keep) == 6
    points, normals, tri, states = points[keep], normals[keep], tri[keep], states[keep]
    caster = cornell_solved.dynamics.caster
    plain = path_values(IndirectTracer(cornell, max_bounces=8, caster=caster), points, normals, 60_000, seed=110,
                        triangles=tri)[0]
    tr = IndirectTracer(cornell, "GUIDED", max_bounces=8, caster=caster, guide=guide, splitting=field)
    values = path_values(tr, points, normals, 30_000, seed=111, states=states, triangles=tri)[0]
    agree(plain, values)


# ---- (b) a wrong V costs efficiency, never the mean ----------------------------------------------

@pytest.mark.parametrize("bad", ["random", "inverted"])
def test_splitting_with_a_wrong_field_keeps_the_mean(narrow, bad):
    """V random (uniform in [0, max V] at every state) or inverted (V_max V_min / V): the window
    splits and kills the wrong paths, and the means still agree with plain path tracing."""
    field = randomised(narrow.field) if bad == "random" else inverted(narrow.field)
    record = Recorder()
    mp = pytest.MonkeyPatch()
    mp.setattr(tracer_module, "splitting_window", record)
    try:
        values = guided(narrow, field, 30_000, seed=120 if bad == "random" else 121)[0]
    finally:
        mp.undo()
    agree(narrow.plain, values, resolved=0.15)
    assert np.any(np.concatenate(record.copies) > 1) and np.any(np.concatenate(record.survival) < 1)


# ---- (c) the window's contract -------------------------------------------------------------------

def test_window_contract():
    """``splitting.window`` on 200 000 rows of ratios over twelve decades, known or not, with and
    without roulette: unknown rows p = 1, n = 1; copies integers in [1, MAX_COPIES], more than one
    only where known and r > 1 (then MAX_COPIES from r >= MAX_COPIES on, else floor(r + u));
    survival in [SURVIVAL_FLOOR, 1], below 1 only where known, roulette allowed and r < 1, and
    there exactly max(r, SURVIVAL_FLOOR); the copies' mean count is r for 1 < r < MAX_COPIES."""
    rng = np.random.default_rng(7)
    k = 200_000
    ratio = 10.0 ** rng.uniform(-6, 6, k)
    ratio[:1000] = 0.0
    ratio[1000:2000] = 1.0
    known = rng.random(k) < 0.7
    roulette = rng.random(k) < 0.5
    p, n = splitting.window(ratio, known, roulette, np.random.default_rng(8))
    assert p.shape == n.shape == (k,) and np.issubdtype(n.dtype, np.integer)
    assert np.all(p[~known] == 1.0) and np.all(n[~known] == 1)
    assert n.min() >= 1 and n.max() == MAX_COPIES
    assert np.all(n[(n > 1)] > 0) and np.all((known & (ratio > 1))[n > 1])
    assert np.all(n[known & (ratio >= MAX_COPIES)] == MAX_COPIES)
    mid = known & (ratio > 1) & (ratio < MAX_COPIES)
    assert np.all((n[mid] == np.floor(ratio[mid])) | (n[mid] == np.floor(ratio[mid]) + 1))
    assert np.all(n[known & (ratio <= 1)] == 1)
    assert p.min() >= SURVIVAL_FLOOR and p.max() <= 1.0
    low = known & roulette & (ratio < 1)
    assert np.all((p < 1) <= low)
    np.testing.assert_array_equal(p[low], np.maximum(ratio[low], SURVIVAL_FLOOR))
    assert np.all(p[~roulette] == 1.0) and np.all(p[ratio >= 1] == 1.0)
    # the mean number of copies at fixed r in (1, MAX_COPIES) is r (floor(r + u))
    for r in (1.01, 1.3, 1.75):
        m = splitting.window(np.full(k, r), np.ones(k, bool), np.zeros(k, bool), np.random.default_rng(9))[1]
        assert abs(m.mean() - r) <= K * m.std() / np.sqrt(k), (r, m.mean())


def test_paths_window_keeps_every_paths_expected_weight():
    """``_Paths.window`` (the tracer's use of the window) on 12 kinds of rows, 40 000 of each:
    V unknown at the vertex or the texel, ratios far below, below, near and above one, with and
    without the roulette vertex: per kind the copies' and survivors' β summed, averaged over the
    rows, is the rows' β (within 5 s.e.); copies get new path numbers beyond all earlier ones,
    owned by their parent's texel path, with light rows of their own (zero), and ``gathered``
    adds them back to the texel paths; before ``rr_start`` no known row is killed."""
    v_vertex = np.array([0.0, 1e-3, 0.05, 0.3, 0.9, 1.0, 1.5, 3.0, 20.0, 0.5, 0.5, 2.0])
    v_texel = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 1.0])
    lum_beta = np.array([0.8, 0.9, 0.6, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.4, 0.7, 0.9])
    kinds, per = len(v_vertex), 40_000
    field = SplitField(value=v_vertex, locator=None)
    for bounce, rr_start in ((3, 3), (1, 3)):
        tr = SimpleNamespace(splitting=field, rr_start=rr_start)
        kind = np.repeat(np.arange(kinds), per)
        m = len(kind)
        paths = _Paths(np.take(v_texel, kind).astype(np.float64))
        beta = (np.take(lum_beta, kind)[:, None] * np.array([1.0, 1.0, 1.0])).astype(np.float32)
        beta[::2] *= np.float32(0.5)
        L = np.zeros((m, 3), np.float32)
        idx = np.arange(m)
        L2, (new_idx, new_beta, rows) = paths.window(tr, L, idx, beta, kind, bounce, np.random.default_rng(bounce),
                                                     None, None)
        assert np.all(np.diff(rows) >= 0)
        assert len(L2) == len(paths.owner) == m + (len(rows) - len(np.unique(rows)))
        assert len(np.unique(new_idx)) == len(new_idx)
        first = np.r_[True, rows[1:] != rows[:-1]]
        np.testing.assert_array_equal(new_idx[first], rows[first])      # the first copy keeps its number
        assert np.all(new_idx[~first] >= m)
        np.testing.assert_array_equal(paths.owner[new_idx], rows)       # every copy's texel path
        assert not np.any(L2[m:])
        total = np.zeros(m)
        np.add.at(total, rows, new_beta[:, 1].astype(np.float64))
        for j in range(kinds):
            t = total[kind == j]
            b = beta[kind == j, 1].astype(np.float64)
            assert abs(t.mean() - b.mean()) <= K * t.std() / np.sqrt(per) + 1e-6 * b.mean(), (bounce, j, t.mean(),
                                                                                             b.mean())
        known = (v_vertex > 0) & (v_texel > 0)
        if bounce < rr_start:     # no roulette yet: every row survives
            assert np.all(np.isin(np.arange(m), rows))
        else:
            assert not np.all(np.isin(np.flatnonzero(np.take(known, kind)), rows))
        ones = np.ones_like(L2)
        back = paths.gathered(ones)
        np.testing.assert_array_equal(back[:, 0], np.bincount(paths.owner, minlength=m)[:m].astype(np.float32))


# ---- (d) it splits, and it pays ------------------------------------------------------------------

def test_splitting_happens_and_lowers_the_variance_through_the_hatch(narrow):
    """Through the hatch the window splits paths (copies > 1 at some vertices, more vertices
    shaded than without it at the same paths) and its roulette ends others; the relative variance
    per path of the six RoomAFloor points falls below 0.8 of GUIDED without splitting (measured
    at 40 000 paths per point over seeds: 0.33 - 0.62)."""
    record = Recorder()
    mp = pytest.MonkeyPatch()
    mp.setattr(tracer_module, "splitting_window", record)
    try:
        split_values, split_stats = guided(narrow, narrow.field, 40_000, seed=130)
    finally:
        mp.undo()
    plain_values, plain_stats = guided(narrow, None, 40_000, seed=131)
    copies, survival = np.concatenate(record.copies), np.concatenate(record.survival)
    assert np.count_nonzero(copies > 1) > 0.01 * split_stats.paths
    assert np.any(survival < 1) and survival.min() >= SURVIVAL_FLOOR
    assert split_stats.vertices > 1.02 * plain_stats.vertices, (split_stats.vertices, plain_stats.vertices)
    assert split_stats.rays > plain_stats.rays
    rv_split, rv_plain = relative_variance(split_values), relative_variance(plain_values)
    assert rv_split < 0.8 * rv_plain, (rv_split, rv_plain)


# ---- (e) where it is off -------------------------------------------------------------------------

def test_splitting_is_built_for_guided_physical_bakes_only(cornell, cornell_solved):
    """``driver.make_tracer``: GUIDED (PHYSICAL costs, ``Settings.splitting`` on by default) has
    the field; not with splitting off, with Cycles' sample clamp (either limit), in UNGUIDED,
    FINAL_GATHER and RESIDUAL, or with THESIS costs; the tracer drops a given field with the
    clamp and in the gather modes."""
    assert Settings().splitting is True
    assert baking.make_tracer(cornell, small(bake_mode="GUIDED"), cornell_solved)[0].splitting is not None
    for settings in (small(bake_mode="GUIDED", splitting=False), small(bake_mode="GUIDED", clamp_indirect=1.0),
                     small(bake_mode="GUIDED", clamp_direct=1.0), small(bake_mode="UNGUIDED"),
                     small(bake_mode="FINAL_GATHER"), small(bake_mode="RESIDUAL")):
        tracer = baking.make_tracer(cornell, settings, cornell_solved)[0]
        assert tracer.splitting is None, settings
    thesis = pipeline.run_all(cornell, Settings(point_count=256, cost_mode="THESIS"))
    assert baking.make_tracer(cornell, small(bake_mode="GUIDED"), thesis)[0].splitting is None
    field = SplitField.from_lmdp(cornell, cornell_solved)
    guide = build_guide(cornell, cornell_solved)
    clamp = SampleClamp.from_settings(small(clamp_indirect=1.0))
    assert clamp.active
    assert IndirectTracer(cornell, "GUIDED", guide=guide, splitting=field, clamp=clamp).splitting is None
    assert IndirectTracer(cornell, "GUIDED", guide=guide, splitting=field).splitting is field
    gather_tracer = baking.make_tracer(cornell, small(bake_mode="FINAL_GATHER"), cornell_solved)[0]
    assert IndirectTracer(cornell, "FINAL_GATHER", guide=guide, gather=gather_tracer.gather,
                          splitting=field).splitting is None
    residual = baking.make_tracer(cornell, small(bake_mode="RESIDUAL"), cornell_solved)[0]
    assert IndirectTracer(cornell, "RESIDUAL", control=residual.control, splitting=field).splitting is None


@pytest.mark.parametrize("case", ["clamp_indirect", "FINAL_GATHER", "RESIDUAL"])
def test_splitting_setting_changes_nothing_where_it_is_off(cornell, cornell_solved, case):
    """With the clamp (GUIDED) and in FINAL_GATHER / RESIDUAL the bake with ``splitting`` on is
    the same bytes as with it off."""
    if case == "clamp_indirect":
        settings = small(bake_mode="GUIDED", clamp_indirect=1.0, seed=5)
    else:
        settings = small(bake_mode=case, seed=5)
    a = baked(cornell, settings, cornell_solved, threads=2)
    np.testing.assert_array_equal(a, baked(cornell, replace(settings, splitting=False), cornell_solved, threads=2))


# ---- (f) determinism -----------------------------------------------------------------------------

def baked(scene, settings, lmdp=None, names=("Floor",), threads=None):
    result = baking.bake(scene, list(names), settings, lmdp, threads=threads)
    return np.concatenate([o.image.ravel() for o in result.objects])


def test_guided_splitting_bake_is_byte_identical_whatever_the_threads(narrow, monkeypatch):
    """``driver.bake`` GUIDED + splitting (+ light connections 0.5) of RoomAFloor, many small
    units finishing out of order: the same bytes with 1 and 2 threads, other bytes with another
    seed, and other bytes without splitting (it is on)."""
    monkeypatch.setattr(baking, "PATHS_PER_UNIT", 256)
    settings = small(bake_mode="GUIDED", bake_samples=8, seed=3)
    assert settings.splitting and settings.light_share > 0
    assert baking.make_tracer(narrow.scene, settings, narrow.lmdp)[0].splitting is not None
    names = ("RoomAFloor",)
    a = baked(narrow.scene, settings, narrow.lmdp, names, threads=1)
    np.testing.assert_array_equal(a, baked(narrow.scene, settings, narrow.lmdp, names, threads=2))
    assert not np.array_equal(a, baked(narrow.scene, replace(settings, seed=4), narrow.lmdp, names, threads=2))
    assert not np.array_equal(a, baked(narrow.scene, replace(settings, splitting=False), narrow.lmdp, names,
                                       threads=2))


# ---- (g) glossy ----------------------------------------------------------------------------------

def test_glossy_box_guided_splitting_keeps_the_mean():
    """GLOSSY_BOX (glossy floor, metallic sphere), 8 bounces, Cycles' glossy limit 4: six floor
    points, 60 000 plain UNGUIDED paths each against 30 000 GUIDED + splitting, in which the
    glossy vertices' BSDF rows follow the copies (``GlossyRows.select`` with repeated rows):
    the same means within 5 s.e."""
    scene, lmdp, guide, field, points, normals, tri, states = solved_points("GLOSSY_BOX", "Floor", 2)
    caster = lmdp.dynamics.caster
    plain = path_values(IndirectTracer(scene, max_bounces=8, caster=caster, glossy_bounces=4), points, normals,
                        60_000, seed=140, triangles=tri)[0]
    repeated = []
    select = tracer_module.GlossyRows.select

    def recording(self, index):
        index = np.asarray(index)
        repeated.append(bool(len(index) > 1 and np.any(index[1:] == index[:-1])))
        return select(self, index)

    mp = pytest.MonkeyPatch()
    mp.setattr(tracer_module.GlossyRows, "select", recording)
    try:
        tr = IndirectTracer(scene, "GUIDED", max_bounces=8, caster=caster, guide=guide, splitting=field,
                            glossy_bounces=4)
        values, stats = path_values(tr, points, normals, 30_000, seed=141, states=states, triangles=tri)
    finally:
        mp.undo()
    assert stats.glossy_vertices > 0 and any(repeated)
    agree(plain, values)
