"""lmdp.bake against Cycles' own bake of the same texels (issue 5, Accuracy).

Reference: ``bake_cycles(type='DIFFUSE', pass_filter={'INDIRECT'})`` with adaptive sampling off,
indirect clamping off (``sample_clamp_indirect = 0``: Cycles' default of 10 clips bright paths and
biases the reference low) and the same path length on both sides (``max_bounces`` = 8 for Cycles'
total and diffuse bounces and for the engine; Cycles' own defaults are 12 total / 4 diffuse).
Each reference is two bakes with seeds 1 and 2, cached in ``out/test_cache/cycles`` (ignored by
git, removed by ``make clean``) under a key of everything that changes it: scene fingerprint,
object, resolution, samples, seed, bounces and the bpy version.

Tolerances come from the estimates' own variance, never from guesses:

* the engine's per-texel standard error comes from its independent sample batches
  (``ObjectBake.standard_error``);
* Cycles' from its two seeds: the mean of the two bakes has per-texel variance ``(a - b)² / 4``;
* a mean over n of Cycles' texels has variance ``Σ var_i / n²``; the engine's from its batches'
  means of the same texels (``ObjectBake.mean_and_error``: with path reuse a tile's texels share
  paths, so they are not independent); bounds are 5 of those standard errors.

The Cornell box's light hangs 5 mm below the ceiling and mesh emission is two-sided (Cycles), so
the ceiling around it glows: rare, very bright paths make every estimator's error heavy-tailed;
the sample counts below keep several thousand such paths per bake so the batch variances hold.
"""
import hashlib
import os

import bpy
import numpy as np
import pytest

from helpers import select

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CACHE = os.path.join(ROOT, "out", "test_cache", "cycles")
BOUNCES = 8
K = 5.0


def build(kind, lmdp_ext):
    assert bpy.ops.lmdp.add_demo_scene(kind=kind) == {'FINISHED'}
    scene = bpy.context.scene
    scene.cycles.sample_clamp_indirect = 0.0
    return scene


def reference(lmdp_ext, demo, name, resolution, samples, seeds=(1, 2)):
    """Cycles' DIFFUSE/INDIRECT bakes of ``name`` with ``seeds``, cached; (len(seeds), R, R, 3)."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    checks = lmdp_ext.sub("lmdp_addon.bake.checks")
    scene = bpy.context.scene
    arrays = extract.extract_scene(bpy.context, [bpy.data.objects[name]])
    out = []
    for seed in seeds:
        key = "|".join(map(str, (checks.scene_fingerprint(arrays), name, resolution, samples, seed,
                                 BOUNCES, scene.cycles.sample_clamp_indirect, bpy.app.version_string)))
        path = os.path.join(CACHE, hashlib.sha1(key.encode()).hexdigest()[:20] + ".npy")
        if os.path.exists(path):
            out.append(np.load(path))
            continue
        px = demo.bake_cycles(bpy.context, bpy.data.objects[name], 'DIFFUSE', ('INDIRECT',), resolution,
                              samples=samples, margin=0, max_bounces=BOUNCES, seed=seed)[..., :3]
        os.makedirs(CACHE, exist_ok=True)
        np.save(path, px.astype(np.float32))
        out.append(px)
    return np.stack(out)


def lmdp_bake(lmdp_ext, name, mode, resolution, samples, seed=11, **settings):
    scene = bpy.context.scene
    s = scene.lmdp
    s.bake_mode = mode
    s.bake_resolution = resolution
    s.bake_samples = samples
    s.bake_margin = 0
    s.max_bounces = BOUNCES
    s.seed = seed
    for key, value in settings.items():
        setattr(s, key, value)
    select([bpy.data.objects[name]])
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    return lmdp_ext.sub("operators.session").session_for(scene).require("bake").object(name)


class Texels(np.ndarray):
    """The engine's texel values, carrying the variance of their mean (``mean_var``, (3,))."""


def compare(ob, refs):
    """Per-texel engine value (with the variance of its mean from the batches, ``Texels``),
    Cycles value and their per-texel variances."""
    ts = ob.texels
    cyc = refs.mean(axis=0)[ts.row, ts.col].astype(np.float64)
    var_c = ((refs[0] - refs[1]) ** 2 / 4.0)[ts.row, ts.col] if len(refs) == 2 else np.zeros_like(cyc)
    ours = ob.value.astype(np.float64).view(Texels)
    ours.mean_var = ob.mean_and_error()[1] ** 2
    var_o = ob.standard_error.astype(np.float64) ** 2
    return ours, cyc, var_o, var_c


def design_effect(ours, var_o):
    """How much the texels' correlation (path reuse) widens the error of a texel average: the
    batch variance of the mean over the independent-texel one (about 1 without path reuse)."""
    return float(np.max(ours.mean_var / (var_o.sum(axis=0) / len(var_o) ** 2)))


def assert_means_agree(ours, cyc, var_o, var_c):
    """``ours`` from :func:`compare` carries the variance of its mean from the batches; other
    independent per-texel estimates (``var_o``) give ``Σ var_o / n²``."""
    n = len(ours)
    diff = np.asarray(ours).mean(axis=0) - cyc.mean(axis=0)
    mean_var = getattr(ours, "mean_var", None)
    sigma = np.sqrt((var_o.sum(axis=0) / n ** 2 if mean_var is None else mean_var) + var_c.sum(axis=0) / n ** 2)
    assert np.all(np.abs(diff) <= K * sigma), f"mean difference {diff} vs {K} x sigma {sigma}"
    return diff / cyc.mean(axis=0), sigma / cyc.mean(axis=0)


@pytest.mark.parametrize("mode", ["UNGUIDED", "GUIDED", "RESIDUAL"])
def test_cornell_floor_matches_cycles_at_low_resolution(fresh_scene, lmdp_ext, demo, mode):
    """The default suite's end-to-end check: Blender scene -> lmdp.bake -> same texels and the
    same mean as Cycles within 5 standard errors of both estimates; per texel, the squared
    differences are as large as the two variance estimates predict: E[(ours - cyc)²] =
    var_ours + var_cyc for unbiased estimates, so the texel mean of the squared difference minus
    the estimated variances is 0 within 5 standard errors (computed from the texels, widened by
    the design effect of path reuse's correlated texels)."""
    build("CORNELL_BOX", lmdp_ext)
    refs = reference(lmdp_ext, demo, "Floor", 16, 1024)
    fresh_scene.lmdp.point_count = 1024
    if mode == "GUIDED":
        select([o for o in bpy.data.objects if o.type == 'MESH' and o.name != "Light"])
        assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    ob = lmdp_bake(lmdp_ext, "Floor", mode, 16, 512)      # RESIDUAL solves the scene itself first
    covered = np.zeros((16, 16), bool)
    covered[ob.texels.row, ob.texels.col] = True
    assert covered.all()  # the floor's UVs cover the image, in Cycles' mapping too
    ours, cyc, var_o, var_c = compare(ob, refs)
    assert_means_agree(ours, cyc, var_o, var_c)
    excess = np.asarray(((ours - cyc) ** 2 - var_o - var_c).sum(axis=1))
    deff = max(design_effect(ours, var_o), 1.0)
    assert abs(excess.mean()) <= K * excess.std() * np.sqrt(deff / len(excess)), (excess.mean(), deff)


# -- slow: convergence at high sample counts ----------------------------------------------------------

def relative_rmse(ours, cyc, var_c):
    """RMSE of the engine against Cycles relative to Cycles' mean, with the reference's own
    noise removed (E[(ours - cyc)²] = var_ours + bias² + var_cyc)."""
    mse = np.mean((ours - cyc) ** 2) - np.mean(var_c)
    return np.sqrt(max(mse, 0.0)) / cyc.mean()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["Floor", "TallBox"])
@pytest.mark.parametrize("mode", ["UNGUIDED", "GUIDED"])
def test_converges_to_cycles_at_high_samples(fresh_scene, lmdp_ext, demo, name, mode):
    """Mean within 1 % of Cycles' (and within 5 standard errors), and the relative RMSE falls like
    1/sqrt(samples): from N to 4N samples it halves, within 5 standard errors of the ratio
    (propagated from the per-texel squared errors)."""
    build("CORNELL_BOX", lmdp_ext)
    R = 32
    refs = reference(lmdp_ext, demo, name, R, 8192)
    if mode == "GUIDED":
        select([o for o in bpy.data.objects if o.type == 'MESH' and o.name != "Light"])
        assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    errors = []
    for samples in (256, 1024, 4096):
        ob = lmdp_bake(lmdp_ext, name, mode, R, samples)
        ours, cyc, var_o, var_c = compare(ob, refs)
        rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
        sq = ((ours - cyc) ** 2 - var_c).mean(axis=1)
        errors.append((samples, sq.mean(), sq.std() / np.sqrt(len(sq)), rel))
    assert np.all(np.abs(errors[-1][3]) < 0.01), f"mean bias {errors[-1][3]} at 4096 samples"
    for (n1, m1, s1, _), (n2, m2, s2, _) in zip(errors, errors[1:]):
        ratio = m1 / m2  # squared error: 4 for a 4x sample increase
        sigma = ratio * np.sqrt((s1 / m1) ** 2 + (s2 / m2) ** 2)
        assert abs(ratio - n2 / n1) <= K * sigma, (n1, n2, ratio, sigma, errors)


@pytest.mark.slow
@pytest.mark.parametrize("kind, name", [("CORNELL_BOX", "TallBox"), ("NARROW_OPENING", "RoomAFloor"),
                                        ("HEAVY", "Floor")])
def test_residual_is_unbiased_against_cycles(fresh_scene, lmdp_ext, demo, kind, name):
    """RESIDUAL (the solution as a control variate, issue 20) on three scenes: the mean of the
    texels within 5 standard errors of both estimates and within 2 % of Cycles' 2 x 4096-sample
    bake. The bake solves the scene itself (states on every mesh, the default 2048 points)."""
    build(kind, lmdp_ext)
    refs = reference(lmdp_ext, demo, name, 16, 4096)
    ob = lmdp_bake(lmdp_ext, name, "RESIDUAL", 16, 4096)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"RESIDUAL vs Cycles, {kind} {name}: {100 * rel} % ± {100 * rel_sigma} % (1 s.e.)")
    assert np.all(np.abs(rel) < 0.02), rel


def assert_unbiased_where_resolved(ob, refs, label):
    """The mean of ``ob``'s texels within 5 standard errors of both estimates of Cycles' bake
    ``refs`` (``assert_means_agree``) and within 2 % where one standard error is below 0.5 %."""
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"{label}: {100 * rel} % ± {100 * rel_sigma} % (1 s.e.)")
    if np.all(rel_sigma < 0.005):
        assert np.all(np.abs(rel) < 0.02), rel


@pytest.mark.slow
@pytest.mark.parametrize("kind, name", [("CORNELL_BOX", "TallBox"), ("NARROW_OPENING", "RoomAFloor"),
                                        ("HEAVY", "Floor")])
def test_default_bake_with_light_connections_is_unbiased_against_cycles(fresh_scene, lmdp_ext, demo, kind, name):
    """The default bake (UNGUIDED with light connections, ``light_share`` 0.5, issue 20) on the
    three scenes of the RESIDUAL test: the mean of the texels within 5 standard errors of both
    estimates of Cycles' 2 x 4096-sample bake, and within 2 % where the comparison resolves it
    (1 s.e. below 0.5 %: the Cornell and heavy boxes, about 0.25 %; through the narrow opening
    one s.e. is about 1.5 %; per channel, plain path tracing was -0.1..+1.3 % off for seed 11 and
    +0.9..+3.3 % for seed 12, with connections +2.6..+4.8 % and -0.9..-0.1 %), and connections
    were traced."""
    build(kind, lmdp_ext)
    assert fresh_scene.lmdp.light_share == 0.5
    refs = reference(lmdp_ext, demo, name, 16, 4096)
    ob = lmdp_bake(lmdp_ext, name, "UNGUIDED", 16, 4096)
    assert ob.stats.connections > 0
    assert_unbiased_where_resolved(ob, refs, f"UNGUIDED + light connections vs Cycles, {kind} {name}")


@pytest.mark.slow
@pytest.mark.parametrize("kind, name, solved", [("CORNELL_BOX", "TallBox", False), ("NARROW_OPENING", "RoomAFloor", True),
                                                ("HEAVY", "Floor", False)])
def test_the_default_auto_bake_is_unbiased_against_cycles(fresh_scene, lmdp_ext, demo, kind, name, solved):
    """The default mode, AUTO (``bake/auto.py``), on the three scenes of the RESIDUAL test: the
    mean of the texels within 5 standard errors of both estimates of Cycles' 2 x 4096-sample bake
    and within 2 % where the comparison resolves it (1 s.e. below 0.5 %). Through the narrow
    opening its pilot is noisy, so it solves the LMDP during the bake and traces the rest GUIDED
    with the solution's roulette and splitting; the boxes stay unguided."""
    build(kind, lmdp_ext)
    assert fresh_scene.lmdp.bake_mode == 'AUTO'
    refs = reference(lmdp_ext, demo, name, 16, 4096)
    ob = lmdp_bake(lmdp_ext, name, "AUTO", 16, 4096)
    auto = lmdp_ext.sub("operators.session").session_for(fresh_scene).require("bake").auto
    assert auto.solved == solved and (auto.mode == "GUIDED") == solved, auto
    assert_unbiased_where_resolved(ob, refs, f"AUTO vs Cycles, {kind} {name} ({auto.sentence()})")


@pytest.mark.slow
def test_guided_has_lower_variance_than_unguided_through_a_narrow_opening(fresh_scene, lmdp_ext):
    """Room A is lit only through the hatch. Same texels, same samples, 8 x 8 strata: GUIDED's
    per-texel variances (from its batches) are lower than UNGUIDED's. Each texel's log variance
    ratio is symmetric about 0 when the variances are equal (a log F(7, 7) variable); their mean
    over the texels must be below 0 by 5 of its standard errors (computed from the texels)."""
    build("NARROW_OPENING", lmdp_ext)
    select([o for o in bpy.data.objects if o.type == 'MESH' and o.name != "Light"])
    fresh_scene.lmdp.strata_u = fresh_scene.lmdp.strata_v = 8
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    un = lmdp_bake(lmdp_ext, "RoomAFloor", "UNGUIDED", 64, 128)
    gu = lmdp_bake(lmdp_ext, "RoomAFloor", "GUIDED", 64, 128)
    up = un.texels.normal[:, 2] > 0.5
    vu = (un.standard_error.astype(float) ** 2).sum(axis=1)[up]
    vg = (gu.standard_error.astype(float) ** 2).sum(axis=1)[up]
    lit = (vu > 0) & (vg > 0)
    log_ratio = np.log(vg[lit] / vu[lit])
    n = lit.sum()
    print(f"narrow opening: median variance ratio GUIDED/UNGUIDED {np.exp(np.median(log_ratio)):.3f} "
          f"over {n} texels")
    assert log_ratio.mean() < -K * log_ratio.std() / np.sqrt(n), (log_ratio.mean(), log_ratio.std(), n)


@pytest.mark.slow
def test_final_gather_bias_on_the_cornell_floor(fresh_scene, lmdp_ext, demo):
    """FINAL_GATHER is biased by the discretisation of z: the relative mean bias (luminance)
    against Cycles on the floor lies in :data:`FINAL_GATHER_BIAS_RANGE` at the default 2048
    points and at 8192."""
    build("CORNELL_BOX", lmdp_ext)
    refs = reference(lmdp_ext, demo, "Floor", 32, 8192)
    biases = []
    for points in (2048, 8192):
        select([o for o in bpy.data.objects if o.type == 'MESH' and o.name != "Light"])
        fresh_scene.lmdp.point_count = points
        assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
        ob = lmdp_bake(lmdp_ext, "Floor", "FINAL_GATHER", 32, 256)
        ours, cyc, var_o, var_c = compare(ob, refs)
        lum = np.array([0.2126, 0.7152, 0.0722])
        biases.append(float((ours.mean(axis=0) - cyc.mean(axis=0)) @ lum / (cyc.mean(axis=0) @ lum)))
    print(f"FINAL_GATHER relative bias (luminance) at 2048 / 8192 points: {biases}")
    low, high = FINAL_GATHER_BIAS_RANGE
    assert all(low < b < high for b in biases), biases


#: Relative bias bound of FINAL_GATHER on the Cornell floor: four standard deviations of the
#: bias's spread over seeds (the bias is the discretisation's own and its sign depends on where
#: the points fall; ``bench/bias_map.py CORNELL_BOX Floor --modes FINAL_GATHER`` maps it).
FINAL_GATHER_BIAS_RANGE = (-0.02, 0.02)
