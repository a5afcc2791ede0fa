"""Cycles' sample clamp (issue 19, item 3): the bake clamps as Cycles' own bake of the same texels.

Scene: the Cornell box with its ceiling light replaced by a 2 cm "Spark" (emission 5000, two-sided)
5 cm above the tall box: the floor never sees it, so all its light has bounced, and the paths
that reach the tall box's top right under the spark carry rare, very bright contributions, the
fireflies the clamp is for. Light paths: the demo's 8 / 8 on both sides, Cycles' defaults for
everything else (light tree, Min Light Bounces 0 unless a test sets it).

A clamp is a nonlinear function of each contribution, so the clamped means agree only where the
samples are distributed as Cycles'. With the clamp the engine therefore also ends paths by
Cycles' Russian roulette (``IndirectTracer._cycles_roulette``; docs/design.md, "Sample clamp").
Tolerances as in ``test_bake_vs_cycles``: the mean within 2 % and within 5 standard errors of both
estimates (engine batches, Cycles' two seeds). Each test also shows that the clamp matters: the
unclamped bake is more than 10 % away.
"""
import hashlib
import os

import bpy
import numpy as np
import pytest

from helpers import add_material, select
from test_bake_vs_cycles import CACHE, assert_means_agree, compare

RESOLUTION = 16
SPARK = dict(size=0.02, gap=0.05, strength=5000.0)


def spark_box():
    """The Cornell box lit only by the spark above the tall box (module docstring)."""
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    bpy.data.objects.remove(bpy.data.objects["Light"])
    bpy.ops.mesh.primitive_plane_add(size=SPARK["size"], location=(-0.17, 0.12, 0.6 + SPARK["gap"]))
    spark = bpy.context.active_object
    spark.name = "Spark"
    spark.data.materials.append(add_material("Spark", emission=SPARK["strength"]))
    scene = bpy.context.scene
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0
    return scene


def clamped_reference(lmdp_ext, demo, name, pass_filter, samples, seeds=(1, 2)):
    """Cycles' DIFFUSE bakes of ``name`` with the scene's clamps, cached under a key of the scene,
    the object, the settings, both clamps, Min Light Bounces and the bpy version; (len(seeds), R, R, 3)."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    checks = lmdp_ext.sub("lmdp_addon.bake.checks")
    cycles = bpy.context.scene.cycles
    arrays = extract.extract_scene(bpy.context, [bpy.data.objects[name]])
    out = []
    for seed in seeds:
        key = "|".join(map(str, (checks.scene_fingerprint(arrays), name, RESOLUTION, samples, seed,
                                 cycles.max_bounces, cycles.diffuse_bounces, cycles.sample_clamp_direct,
                                 cycles.sample_clamp_indirect, cycles.min_light_bounces, sorted(pass_filter),
                                 bpy.app.version_string)))
        path = os.path.join(CACHE, hashlib.sha1(key.encode()).hexdigest()[:20] + ".npy")
        if not os.path.exists(path):
            px = demo.bake_cycles(bpy.context, bpy.data.objects[name], 'DIFFUSE', tuple(pass_filter), RESOLUTION,
                                  samples=samples, margin=0, seed=seed)[..., :3]   # the scene's light paths
            os.makedirs(CACHE, exist_ok=True)
            np.save(path, px.astype(np.float32))
        out.append(np.load(path))
    return np.stack(out)


def default_bake(lmdp_ext, name, samples, mode="UNGUIDED", seed=11, **settings):
    """lmdp.bake of ``name`` with the scene's light paths (the default); (ObjectBake, BakeResult)."""
    scene = bpy.context.scene
    s = scene.lmdp
    s.bake_mode, s.bake_resolution, s.bake_samples, s.bake_margin, s.seed = mode, RESOLUTION, samples, 0, seed
    for key, value in settings.items():
        setattr(s, key, value)
    select([bpy.data.objects[name]])
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    result = lmdp_ext.sub("operators.session").session_for(scene).require("bake")
    return result.object(name), result


def agree_clamped(ob, refs, unclamped, label):
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    effect = unclamped.value.astype(np.float64).mean(axis=0) / cyc.mean(axis=0) - 1.0
    print(f"{label}: ours {ours.mean(axis=0)} cycles {cyc.mean(axis=0)}: {np.round(rel * 100, 2)} % "
          f"± {np.round(rel_sigma * 100, 2)} % (1 s.e.); unclamped {np.round(effect * 100, 1)} %; "
          f"{ob.stats.clamped} contributions clamped")
    assert np.all(np.abs(rel) < 0.02), rel
    assert np.all(effect > 0.10), effect       # the clamp changes this bake: a bake without it fails
    assert ob.stats.clamped > 0


@pytest.mark.parametrize("mode", ["UNGUIDED", "GUIDED", "RESIDUAL"])
def test_indirect_clamp_matches_cycles_on_the_spark_box(fresh_scene, lmdp_ext, demo, mode):
    """The floor's indirect light with Cycles' default indirect clamp 10 (16 % below the
    unclamped value): the default bake follows the scene's clamp and agrees with Cycles'
    clamped bake. GUIDED's samples differ from Cycles' (drawn from u*): its clamp judges each by
    the value Cycles' cosine sample of the same path would have (``tracer._to_cycles``), which
    keeps Cycles' clamped mean. RESIDUAL clamps the same cosine paths;
    its control variate is subtracted unclamped and added back through its own mean, so it
    estimates the same clamped value. Both solve the scene first (a first bake just works)."""
    scene = spark_box()
    scene.cycles.sample_clamp_indirect = 10.0
    refs = clamped_reference(lmdp_ext, demo, "Floor", ("INDIRECT",), 4096)
    scene.lmdp.point_count = 1024
    ob, result = default_bake(lmdp_ext, "Floor", 4096, mode)
    paths = result.stats()["light_paths"]
    assert paths["source"] == "SCENE" and paths["clamp_indirect"] == 10.0 and paths["clamp_applied"] is True
    assert not result.warnings
    scene.cycles.sample_clamp_indirect = 0.0
    unclamped, _ = default_bake(lmdp_ext, "Floor", 256, "UNGUIDED")
    agree_clamped(ob, refs, unclamped, f"spark box floor, indirect clamp 10, {mode}")


@pytest.mark.slow
def test_min_light_bounces_delay_the_roulette_as_in_cycles(fresh_scene, lmdp_ext, demo):
    """Cycles' Min Light Bounces 3 spares the paths' first bounces from its Russian roulette, so
    fewer amplified paths reach the clamp (Cycles' clamped floor rises 5.5 %): the bake reads it
    from the scene and agrees again."""
    scene = spark_box()
    scene.cycles.sample_clamp_indirect = 10.0
    scene.cycles.min_light_bounces = 3
    refs = clamped_reference(lmdp_ext, demo, "Floor", ("INDIRECT",), 4096)
    ob, result = default_bake(lmdp_ext, "Floor", 4096)
    assert result.settings["min_light_bounces"] == 3 and result.stats()["light_paths"]["min_light_bounces"] == 3
    scene.cycles.sample_clamp_indirect = 0.0
    unclamped, _ = default_bake(lmdp_ext, "Floor", 256)
    agree_clamped(ob, refs, unclamped, "spark box floor, indirect clamp 10, Min Light Bounces 3")
    scene.cycles.sample_clamp_indirect, scene.cycles.min_light_bounces = 10.0, 0
    early, _ = default_bake(lmdp_ext, "Floor", 4096)
    assert np.all(ob.value.mean(axis=0) > 1.03 * early.value.mean(axis=0))


def test_indirect_clamp_of_a_point_light_matches_cycles(fresh_scene, lmdp_ext, demo):
    """The spark replaced by a 60 W point light (radius 0) at its place: the lamps' light samples
    go through the same clamp (22 % below the unclamped value at Cycles' default 10)."""
    scene = spark_box()
    bpy.data.objects.remove(bpy.data.objects["Spark"])
    light = bpy.data.lights.new("Bulb", 'POINT')
    light.energy, light.shadow_soft_size = 60.0, 0.0
    bulb = bpy.data.objects.new("Bulb", light)
    bulb.location = (-0.17, 0.12, 0.6 + SPARK["gap"])
    scene.collection.objects.link(bulb)
    scene.cycles.sample_clamp_indirect = 10.0
    refs = clamped_reference(lmdp_ext, demo, "Floor", ("INDIRECT",), 2048)
    ob, result = default_bake(lmdp_ext, "Floor", 2048)
    assert result.stats()["light_paths"]["clamp_indirect"] == 10.0 and not result.warnings
    scene.cycles.sample_clamp_indirect = 0.0
    unclamped, _ = default_bake(lmdp_ext, "Floor", 256)
    agree_clamped(ob, refs, unclamped, "spark box floor lit by a point light, indirect clamp 10")


@pytest.mark.parametrize("mode", ["UNGUIDED", "GUIDED"])
def test_indirect_clamp_on_the_glossy_box_matches_cycles(fresh_scene, lmdp_ext, demo, mode):
    """GLOSSY_BOX (a Principled glossy checker floor and a metallic sphere): paths through its
    glossy vertices sample the BSDF as Cycles does, so their clamped contributions agree too
    (indirect clamp 0.5, 15..21 % below the unclamped value); GUIDED mixes the guide with the
    BSDF there, and the clamp sees Cycles' BSDF sample through p_mix / p_bsdf."""
    assert bpy.ops.lmdp.add_demo_scene(kind='GLOSSY_BOX') == {'FINISHED'}
    scene = bpy.context.scene
    scene.cycles.sample_clamp_indirect = 0.5
    refs = clamped_reference(lmdp_ext, demo, "Floor", ("INDIRECT",), 2048)
    scene.lmdp.point_count = 1024
    ob, result = default_bake(lmdp_ext, "Floor", 2048, mode)
    assert result.stats()["light_paths"]["clamp_indirect"] == 0.5
    scene.cycles.sample_clamp_indirect = 0.0
    unclamped, _ = default_bake(lmdp_ext, "Floor", 512)
    agree_clamped(ob, refs, unclamped, f"glossy box floor, indirect clamp 0.5, {mode}")


@pytest.mark.parametrize("mode", ["UNGUIDED", "GUIDED"])
def test_direct_clamp_matches_cycles_on_a_direct_indirect_bake(fresh_scene, lmdp_ext, demo, mode):
    """The ceiling above the spark, direct + indirect, Cycles' direct clamp 0.5 (indirect off):
    the light samples and the MIS-weighted hits of the texel's own rays are clamped at the
    direct limit (25 % below the unclamped value), as in Cycles' bake. GUIDED: the texel's light
    sample is judged without its guided direction's ratio (it does not depend on it)."""
    scene = spark_box()
    scene.cycles.sample_clamp_direct = 0.5
    refs = clamped_reference(lmdp_ext, demo, "Ceiling", ("DIRECT", "INDIRECT"), 1024)
    scene.lmdp.point_count = 1024
    ob, result = default_bake(lmdp_ext, "Ceiling", 1024, mode, bake_content="DIRECT_INDIRECT")
    paths = result.stats()["light_paths"]
    assert (paths["clamp_direct"], paths["clamp_indirect"]) == (0.5, 0.0)
    scene.cycles.sample_clamp_direct = 0.0
    unclamped, _ = default_bake(lmdp_ext, "Ceiling", 256, bake_content="DIRECT_INDIRECT")
    agree_clamped(ob, refs, unclamped, f"spark box ceiling, direct + indirect, direct clamp 0.5, {mode}")
