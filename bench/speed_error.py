"""Speed against error: every bake method on the same texels of the same scene, against a cached
high-sample Cycles reference of the same bake (issue 6).

For each case (scene, receiver object, resolution, path length):

1. Blender builds the scene from ``operators.adapters.demo_scenes`` and the engine from
   ``lmdp_addon.demo_geometry.build_scene_arrays`` (the same parts; ``tests/addon/test_extract.py``
   checks that Blender's extraction gives back these triangles).
2. The reference: Cycles' bake with ``ref_samples`` samples, made of two independent halves
   (seeds 1 and 2, ``ref_samples / 2`` each), averaged; cached in ``bench/results/reference/``
   under a key of scene, receiver, resolution, samples, bounces, bpy version and a hash of the
   scene's geometry and of ``operators/adapters/demo_scenes.py``. Its noise is estimated from the halves
   (``metrics.reference_noise``).
3. Scored texels: covered in Cycles' reference and in the engine's rasterisation
   (``checks.object_texels``; the two masks are compared and the difference reported) and facing
   up (normal z > 0.5: the floor's top, not the sides or underside of a floor slab).
4. Every method runs its ladder of sample counts ``repeats`` times (``case_repeats`` for a case
   named there; seeds 100, 101, ...; the repeat loop is outermost so that slow drifts of the
   machine spread over all methods). Times are medians over the repeats; the error is the root
   mean square of the repeats' relative RMSEs, corrected for the reference noise; the bias is the
   mean of the repeats' biases.
"""
import hashlib
import time
from dataclasses import dataclass, field

import numpy as np

from . import glossy_scene, metrics, world_scene
from .blender_session import SENTINEL
from .common import RESULTS, ROOT, Stopwatch, log
from .methods import CyclesBake, LMDPBake, lmdp_bake_available

#: Scenes of the suite. ``receiver``: the object whose lightmap is baked and scored.
CASES = {
    "cornell": dict(title="Cornell box, floor", kind="CORNELL_BOX", receiver="Floor"),
    "narrow_opening": dict(title="Narrow opening, floor of the room lit only through the hatch",
                           kind="NARROW_OPENING", receiver="RoomAFloor"),
    "heavy": dict(title="Heavy Cornell box (bumpy, subdivided), floor", kind="HEAVY", receiver="Floor"),
    "sun_hdri": dict(title="Cornell box without its lamp under city.exr, its sun through the open front, floor",
                     kind="CORNELL_BOX", receiver="Floor", world=True),
    "glossy": dict(title="Glossy box: textured glossy floor (an Image Texture), metallic sphere (Principled)",
                   kind="GLOSSY_BOX", receiver="Floor", textured=True),
}

#: Name of the Cycles-with-path-guiding curve.
CYCLES_GUIDED = "Cycles + path guiding"

#: Seeds of the two reference halves, and the first seed of the compared runs.
REFERENCE_SEEDS = (1, 2)
FIRST_SEED = 100


@dataclass
class Profile:
    """How much work a run does (``--quick`` or the full suite)."""

    name: str
    cases: tuple
    resolution: dict            #: case -> pixels
    ref_samples: dict           #: case -> reference samples (two halves)
    repeats: int
    bounces: int
    cycles_ladder: tuple
    #: LMDP methods after Cycles, in run order: dicts with ``mode`` ('UNGUIDED', 'GUIDED',
    #: 'FINAL_GATHER', 'RESIDUAL'), ``name``, ``ladder``, optional ``settings`` (overrides of the
    #: engine's ``Settings`` defaults) and ``cases`` (the cases it runs on; default all).
    lmdp_methods: list = field(default_factory=list)
    #: Sample counts of Cycles with path guiding on (Open PGL), a column beside Cycles, per case
    #: (case key -> ladder; a case not named does not run it).
    cycles_guided_ladder: dict = field(default_factory=dict)
    #: Repeats of a case where it needs more than ``repeats`` (case key -> repeats).
    case_repeats: dict = field(default_factory=dict)


def method_plan(profile, case_key):
    """The methods of one case, in run order: Cycles first, then the profile's LMDP entries."""
    methods = [CyclesBake(profile.cycles_ladder)]
    if profile.cycles_guided_ladder.get(case_key):
        methods.append(CyclesBake(profile.cycles_guided_ladder[case_key], name=CYCLES_GUIDED, guiding=True))
    ok, _ = lmdp_bake_available()
    if not ok:
        return methods
    for entry in profile.lmdp_methods:
        if case_key in entry.get("cases", profile.cases):
            methods.append(LMDPBake(entry["mode"], entry["ladder"], name=entry["name"], **entry.get("settings", {})))
    return methods


@dataclass
class BakeCase:
    key: str
    title: str
    kind: str
    receiver: str
    resolution: int
    bounces: int
    ref_samples: int
    scene: object = None
    blender: object = None
    rows: np.ndarray = None
    cols: np.ndarray = None
    reference: np.ndarray = None       #: (n, 3) at the scored texels
    info: dict = field(default_factory=dict)


# -- reference ----------------------------------------------------------------------------------

def geometry_hash(scene):
    """Hash of the engine's scene arrays and of the Blender scene builder (cache key part)."""
    h = hashlib.blake2b(digest_size=8)
    for a in (scene.vertices, scene.triangles, scene.triangle_albedo, scene.triangle_emission,
              scene.world_radiance):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update("\0".join(scene.object_names).encode())
    if scene.has_glossy():   # the microfacet lobes (Lambertian scenes hash as before)
        m = scene.materials
        for a in (scene.triangle_material, m.kind, m.weight, m.alpha, m.eta, m.f0, m.b, m.multiscatter):
            h.update(np.ascontiguousarray(a).tobytes())
    h.update((ROOT / "operators" / "adapters" / "demo_scenes.py").read_bytes())
    if getattr(scene, "environment", None) is not None:        # the sun + HDRI scene
        for a in scene.environment.fingerprint_arrays():
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(world_scene.SOURCE.read_bytes())
    if getattr(scene, "surface", None) is not None:            # the textured glossy scene
        h.update(scene.surface.fingerprint())
        h.update(glossy_scene.SOURCE.read_bytes())
    return h.hexdigest()


def reference_key(case, blender_version, ghash):
    return (f"{case.kind.lower()}-{case.receiver}-{case.resolution}px-{case.ref_samples}spp-"
            f"{case.bounces}b-bpy{blender_version}-{ghash}")


def load_or_bake_reference(case, cache_dir):
    """The two halves (R, R, 4) of the reference and its metadata, from the cache or baked now."""
    key = reference_key(case, case.blender.version, geometry_hash(case.scene))
    path = cache_dir / f"{key}.npz"
    if path.exists():
        data = np.load(path, allow_pickle=False)
        meta = {"key": key, "cached": True, "file": str(path.relative_to(ROOT)),
                "seconds": [float(s) for s in data["seconds"]], "samples": case.ref_samples,
                "seeds": [int(s) for s in data["seeds"]], "created": str(data["created"])}
        log(f"{case.key}: reference from cache ({path.name})")
        return data["a"], data["b"], meta
    half = case.ref_samples // 2
    halves, seconds = [], []
    for seed in REFERENCE_SEEDS:
        log(f"{case.key}: baking the reference half with seed {seed} ({half} samples) ...")
        with Stopwatch() as sw:
            halves.append(case.blender.bake(case.receiver, case.resolution, half, seed, case.bounces))
        seconds.append(sw.seconds)
        log(f"{case.key}: reference half done in {sw.seconds:.1f} s")
    cache_dir.mkdir(parents=True, exist_ok=True)
    created = time.strftime("%Y-%m-%d %H:%M:%S %Z")
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, a=halves[0], b=halves[1], seconds=np.array(seconds),
                        seeds=np.array(REFERENCE_SEEDS), created=np.array(created))
    tmp.replace(path)
    meta = {"key": key, "cached": False, "file": str(path.relative_to(ROOT)), "seconds": seconds,
            "samples": case.ref_samples, "seeds": list(REFERENCE_SEEDS), "created": created}
    return halves[0], halves[1], meta


def scored_texels(case, ref_a, ref_b):
    """Rows and columns of the scored texels, with the coverage comparison (module docstring)."""
    from lmdp_addon.bake import checks
    index = case.scene.object_names.index(case.receiver)
    texels, _ = checks.object_texels(case.scene, index, case.resolution)
    engine_mask = texels.covered_mask()
    cycles_mask = (ref_a[..., 3] != SENTINEL) & (ref_b[..., 3] != SENTINEL)
    up = np.zeros_like(engine_mask)
    up[texels.row, texels.col] = texels.normal[:, 2] > 0.5
    scored = engine_mask & cycles_mask & up
    rows, cols = np.nonzero(scored)
    coverage = {
        "engine_covered": int(engine_mask.sum()),
        "cycles_covered": int(cycles_mask.sum()),
        "only_engine": int((engine_mask & ~cycles_mask).sum()),
        "only_cycles": int((cycles_mask & ~engine_mask).sum()),
        "scored": int(scored.sum()),
        "scored_rule": "covered by both and facing up (normal z > 0.5)",
    }
    return rows, cols, coverage


# -- running ------------------------------------------------------------------------------------

def prepare_case(key, profile, blender, cache_dir):
    from lmdp_addon import demo_geometry as scenes
    spec = CASES[key]
    case = BakeCase(key=key, title=spec["title"], kind=spec["kind"], receiver=spec["receiver"],
                    resolution=profile.resolution[key], bounces=profile.bounces,
                    ref_samples=profile.ref_samples[key])
    case.scene = scenes.build_scene_arrays(case.kind)
    if case.scene.has_glossy():   # the GGX tables are computed once per process (Blender session): not timed
        from lmdp_addon.bsdf import ggx_tables
        ggx_tables()
    case.blender = blender
    with Stopwatch() as sw:
        blender.load_scene(case.kind)
        if spec.get("world"):
            case.scene = world_scene.build(blender)
        if spec.get("textured"):
            case.scene = glossy_scene.build(blender)
    case.info["blender_scene_seconds"] = sw.seconds
    a, b, meta = load_or_bake_reference(case, cache_dir)
    case.rows, case.cols, coverage = scored_texels(case, a, b)
    ra = a[case.rows, case.cols, :3].astype(np.float64)
    rb = b[case.rows, case.cols, :3].astype(np.float64)
    case.reference = 0.5 * (ra + rb)
    meta["noise_relative_rmse"] = metrics.reference_noise(ra, rb)
    meta["mean"] = [float(x) for x in case.reference.mean(axis=0)]
    case.info.update(reference=meta, coverage=coverage, triangles=int(case.scene.n_triangles))
    log(f"{key}: {coverage['scored']} scored texels, reference noise "
        f"{100 * meta['noise_relative_rmse']:.2f}% relative RMSE")
    return case


def run_case(case, methods, repeats):
    """All methods x ladders x repeats on one case; returns the list of run records."""
    records = []
    failures = {}
    for r in range(repeats):
        seed = FIRST_SEED + r
        for method in methods:
            if method.name in failures:
                continue
            try:
                prepared = method.prepare(case, seed)
            except Exception as exc:  # an engine failure is a result, not a crash of the suite
                failures[method.name] = f"precompute failed: {type(exc).__name__}: {exc}"
                log(f"{case.key}: {method.name}: {failures[method.name]}")
                continue
            for samples in method.ladder:
                try:
                    run = method.bake(case, prepared, samples, seed)
                except Exception as exc:
                    failures[method.name] = f"bake failed at {samples} samples: {type(exc).__name__}: {exc}"
                    log(f"{case.key}: {method.name}: {failures[method.name]}")
                    break
                rmse, bias = metrics.relative_errors(run.values, case.reference)
                total = prepared.total + run.seconds
                records.append({
                    "method": method.name, "family": method.family, "samples": int(samples),
                    "repeat": r, "seed": seed, "seconds": total, "bake_seconds": run.seconds,
                    "precompute_seconds": dict(prepared.seconds), "rel_rmse": rmse, "bias": bias,
                    "info": run.info,
                })
                log(f"{case.key}: {method.name:>28s} {samples:5d} spp  repeat {r}: {total:7.2f} s "
                    f"(precompute {prepared.total:5.2f} s), rel. RMSE {100 * rmse:6.2f}%, bias {100 * bias:+6.2f}%")
            prepared = None
    return records, failures


def summarise(case_result):
    """Per method and sample count: median times, error over repeats, bias (module docstring)."""
    noise = case_result["reference"]["noise_relative_rmse"]
    curves = {}
    for m in case_result["methods"]:
        name = m["name"]
        points = []
        for samples in m["ladder"]:
            runs = [r for r in case_result["records"] if r["method"] == name and r["samples"] == samples]
            if not runs:
                continue
            raw = metrics.combine_repeats([r["rel_rmse"] for r in runs])
            stages = sorted({k for r in runs for k in r["precompute_seconds"]})
            points.append({
                "samples": samples,
                "repeats": len(runs),
                "seconds": metrics.median([r["seconds"] for r in runs]),
                "bake_seconds": metrics.median([r["bake_seconds"] for r in runs]),
                "precompute_seconds": {k: metrics.median([r["precompute_seconds"].get(k, 0.0) for r in runs])
                                       for k in stages},
                "precompute_total": metrics.median([sum(r["precompute_seconds"].values()) for r in runs]),
                "rel_rmse_raw": raw,
                "rel_rmse": metrics.corrected_error(raw, noise),
                "at_noise_floor": bool(raw < 2.0 * noise),
                "bias": float(np.mean([r["bias"] for r in runs])),
                "rays": int(np.median([r["info"].get("rays", 0) for r in runs])),
            })
        curves[name] = points
    return curves


def ratio_table(case_result):
    """For each Cycles sample count N >= 4: every other method's time to reach Cycles' error at
    N, divided by Cycles' time at N (``metrics.time_to_reach``)."""
    curves = case_result["curves"]
    cycles = curves.get("Cycles", [])
    rows = []
    for c in cycles:
        if c["samples"] < 4 or not c["rel_rmse"] > 0:
            continue
        row = {"cycles_samples": c["samples"], "cycles_seconds": c["seconds"], "target_rel_rmse": c["rel_rmse"],
               "target_at_noise_floor": c["at_noise_floor"], "methods": {}}
        for m in case_result["methods"]:
            name = m["name"]
            if name == "Cycles" or not curves.get(name):
                continue
            pts = curves[name]
            cross = metrics.time_to_reach([p["seconds"] for p in pts], [max(p["rel_rmse"], 1e-12) for p in pts],
                                          c["rel_rmse"], bias=pts[-1]["bias"])
            status = cross.status(c["seconds"])
            row["methods"][name] = {"kind": cross.kind, "seconds": cross.seconds,
                                    "ratio": cross.seconds / c["seconds"],
                                    "text": cross.ratio_text(c["seconds"]),
                                    "status": status, "loses": status == "loses"}
        rows.append(row)
    return rows


def run(profile, blender, cache_dir=None):
    """The whole section: returns ``{case key: result}`` (JSON-able)."""
    cache_dir = cache_dir or RESULTS / "reference"
    ok, reason = lmdp_bake_available()
    out = {}
    for key in profile.cases:
        case = prepare_case(key, profile, blender, cache_dir)
        methods = method_plan(profile, key)
        repeats = int(profile.case_repeats.get(key, profile.repeats))
        records, failures = run_case(case, methods, repeats)
        result = {
            "title": case.title, "kind": case.kind, "receiver": case.receiver,
            "resolution": case.resolution, "bounces": case.bounces, "repeats": repeats,
            "triangles": case.info["triangles"], "reference": case.info["reference"],
            "coverage": case.info["coverage"], "blender_scene_seconds": case.info["blender_scene_seconds"],
            "methods": [{"name": m.name, "family": m.family, "ladder": list(m.ladder), "settings": m.describe()}
                        for m in methods],
            "failures": failures, "records": records,
            "lmdp_available": ok, "lmdp_unavailable_reason": reason,
        }
        result["curves"] = summarise(result)
        result["ratios"] = ratio_table(result)
        out[key] = result
    return out
