"""Every check of a bake, run once before any work: :func:`check_bake` returns a :class:`BakePlan`.

The checks raise :class:`~lmdp_addon.errors.SceneError` / :class:`~lmdp_addon.errors.StageOrderError`
with messages written for the user; the plan carries what they computed (the objects' texels)
to the bake, which then runs no check again (``driver.bake(..., plan=plan)``). The operators call
:func:`check_bake` on Blender's main thread and hand the plan to the worker.
"""
import hashlib
from dataclasses import dataclass, field

import numpy as np

from ..errors import BudgetError, SceneError, StageOrderError
from ..settings import BAKE_CONTENTS, BAKE_MODES, OUTPUT_8BIT, OUTPUT_FORMATS
from .clamp import check_clamp, clamp_warnings
from .memory import estimate_bake_bytes
from .resolution import check_resolution_settings, object_resolutions
from .texels import rasterize_texels, texel_count_bound

#: Most texels (summed over objects) whose rasterisation a :class:`BakePlan` keeps for the bake:
#: ``texels.TEXEL_BYTES`` (41 B) each, so at most ~41 MiB held between the check and the bake;
#: objects beyond it are rasterised again when baked.
TEXEL_CACHE_LIMIT = 1 << 20
#: Blender stores UVs as 32-bit floats: a coordinate beyond 2^24 texels of the image
#: (``2**24 / R`` in UV units) cannot be placed within a texel, and only corrupt or
#: world-scale UV maps reach it.
UV_TEXEL_LIMIT = float(1 << 24)


@dataclass
class BakePlan:
    """What :func:`check_bake` found: the bake of ``names`` can start.

    names       object names to bake, in order
    indices     their object indices in the scene
    resolution  ``settings.bake_resolution``
    resolutions object index -> the side R of its lightmap (``resolution.object_resolutions``:
                ``bake_resolution``, or from the texel density), which its texels are for
    atlas       True: the objects share one image (``settings.atlas``), their UVs must not overlap
    texels      object index -> ``(TexelSet, triangles (T_o,))`` (:func:`object_texels`) of the
                objects the check rasterised, up to :data:`TEXEL_CACHE_LIMIT` texels in all
    warnings    messages for the user (the bake goes on)
    memory_bytes  the bake's estimated peak memory (``memory.estimate_bake_bytes``)
    texels_checked  False while the texel checks (coverage, overlapping UVs: they rasterise every
                object) are still to run: :func:`check_texels` runs them, and ``driver.bake``
                does when given such a plan, where the progress can report and cancel them
    """

    names: list
    indices: list
    resolution: int
    texels: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    memory_bytes: int = 0
    texels_checked: bool = True
    texel_warnings: list = field(default_factory=list)   #: what the texel checks said (objects left out)
    resolutions: dict = field(default_factory=dict)
    atlas: bool = False

    def resolution_of(self, index):
        """The lightmap side R of object ``index``."""
        return int(self.resolutions.get(index, self.resolution))


def object_index(scene, name):
    """Index of the object ``name`` in ``scene.object_names`` (SceneError if absent)."""
    try:
        return scene.object_names.index(name)
    except ValueError:
        raise SceneError(f"Object '{name}' is not part of the captured scene (is it hidden?)") from None


def object_texels(scene, index, resolution):
    """Texels of object ``index`` at ``resolution``: ``(TexelSet, triangles (T_o,))``.

    ``triangles`` maps the TexelSet's local triangle indices to the scene's triangles. Triangles
    left out of the scene for non-finite or huge corners (``SceneArrays.usable_triangles``, which
    warns about them) get no texels.
    """
    tris = np.flatnonzero((scene.triangle_object == index) & scene.usable_triangles())
    normals, _ = scene.triangle_geometry()
    ts = rasterize_texels(scene.triangle_uv[tris], scene.corners()[tris], normals[tris], resolution)
    return ts, tris


def uv_overlaps(scene, index, resolution, texels=None):
    """Texels whose centre two or more of the object's UV triangles cover: ``(count, (row, col))``
    of the first of them (None if none).

    Shared edges cover a centre once, so adjacent triangles never count. ``texels``:
    ``object_texels(scene, index, resolution)`` if the caller has it already.
    """
    ts, _ = texels if texels is not None else object_texels(scene, index, resolution)
    count = int(np.count_nonzero(ts.overlap))
    example = (int(ts.row[ts.overlap][0]), int(ts.col[ts.overlap][0])) if count else None
    return count, example


def bad_uv_faces(scene, index, resolution):
    """(k,) scene triangles of object ``index`` whose UVs are non-finite or beyond
    ``UV_TEXEL_LIMIT / resolution`` in magnitude (:data:`UV_TEXEL_LIMIT`), among the triangles
    that get texels (``object_texels``: the scene's usable ones)."""
    tris = np.flatnonzero((scene.triangle_object == index) & scene.usable_triangles())
    uv = scene.triangle_uv[tris].astype(np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~np.all(np.isfinite(uv) & (np.abs(uv) <= UV_TEXEL_LIMIT / int(resolution)), axis=(1, 2))
    return tris[bad]


def scene_fingerprint(scene):
    """Hash of the geometry, shading normals, materials (with their microfacet lobes), world,
    lamps and object names of a SceneArrays (not the selection).

    Shading normals count where they shade: the corner normals of the
    ``SceneArrays.smooth_triangles`` (the others shade with their face normal, exactly as
    without corner normals), so a flat scene hashes as before and its smooth or custom-normal
    variant differs from it.
    """
    h = hashlib.blake2b(digest_size=16)
    for array in (scene.vertices, scene.triangles, scene.triangle_object, scene.triangle_albedo,
                  scene.triangle_emission, scene.triangle_emission_two_sided, scene.world_radiance):
        h.update(np.ascontiguousarray(array).tobytes())
    h.update("\0".join(scene.object_names).encode())
    smooth = scene.smooth_triangles()
    if np.any(smooth):
        h.update(b"\0corner_normals\0")
        h.update(np.flatnonzero(smooth).astype(np.int64).tobytes())
        h.update(np.ascontiguousarray(scene.corner_normals[smooth], dtype=np.float32).tobytes())
    if getattr(scene, "environment", None) is not None:
        h.update(b"\0environment\0")
        for array in scene.environment.fingerprint_arrays():
            h.update(np.ascontiguousarray(array).tobytes())
    if not scene.lamps.empty:   # scenes without lamps hash as before
        h.update(b"\0lamps\0" + "\0".join(scene.lamps.names).encode())
        for array in scene.lamps.arrays():
            h.update(np.ascontiguousarray(array).tobytes())
    if getattr(scene, "surface", None) is not None:
        h.update(b"\0surface\0" + scene.surface.fingerprint())
    if scene.has_glossy():  # microfacet lobes (Lambertian scenes hash as before)
        m = scene.materials
        h.update(b"\0materials\0")
        for array in (scene.triangle_material, m.kind, m.weight, m.alpha, m.eta, m.f0, m.b, m.multiscatter,
                      m.layer, np.float64(m.filter_glossy)):
            h.update(np.ascontiguousarray(array).tobytes())
    return h.hexdigest()


def check_bake(scene, names, settings, lmdp=None, will_solve=False, rasterise=True):
    """Check a bake of the objects ``names`` of ``scene`` before any work; returns its :class:`BakePlan`.

    Checks, in order: the mode, resolution, samples and bounces >= 1, a selection, every object
    has a UV map with finite, not huge coordinates, the bake's memory estimate fits
    ``memory_budget_gb`` (:func:`check_bake_memory`), every object covers at least one texel and
    has no overlapping UVs, the scene has light,
    GUIDED / FINAL_GATHER have a solution and FINAL_GATHER a PHYSICAL one of this very scene.
    ``will_solve``: the caller solves this scene with ``settings`` before baking (Run All), so
    only the cost mode is checked. Each object is rasterised once. ``rasterise=False`` leaves the
    texel checks (the only slow ones: coverage and overlapping UVs) to :func:`check_texels`, so a
    caller on Blender's main thread can run them where they report progress and can be cancelled
    (the operators: in the worker, before any tracing).
    """
    names = list(names)
    R = _check_settings(settings, names)
    indices = [object_index(scene, n) for n in names]
    no_uv = [n for n, i in zip(names, indices) if not scene.object_has_uv[i]]
    if no_uv:
        raise SceneError(f"No UV map on {', '.join(no_uv)}: add one (LMDP > Bake > Create Lightmap UVs, "
                         "or turn on Auto Lightmap UVs) or deselect them; the lightmap is laid out by "
                         "the UV map")
    atlas = bool(getattr(settings, "atlas", False)) and len(names) > 1
    resolutions = object_resolutions(scene, indices, settings, atlas=atlas)
    _check_uv_values(scene, names, indices, resolutions)
    memory = check_bake_memory(scene, names, indices, settings, resolutions)
    texels, skipped = _check_texels(scene, names, indices, resolutions, atlas=atlas) if rasterise else ({}, [])
    if not scene.has_light():
        raise SceneError("The scene has no light to bake: add an emissive material (Emission "
                         "shader or Principled emission), a light (point, spot, sun or area), or a "
                         "non-black world")
    warnings = _check_solution(scene, names, settings, lmdp, will_solve)
    if settings.bake_mode in ("GUIDED", "FINAL_GATHER") and scene.has_glossy():
        warnings.append("Glossy surfaces (Principled specular / metallic, Glossy BSDF): the LMDP solution "
                        "gives each glossy point one unknown per outgoing stratum, so what they reflect "
                        "is resolved to a stratum of the hemisphere (Strata U x V), and without Filter "
                        "Glossy or the glossy bounce limit; "
                        + ("Final Gather continues paths that hit them and reads the solution only at "
                           "diffuse hits (its bias grows with what glossy surfaces reflect there)"
                           if settings.bake_mode == "FINAL_GATHER" else
                           "the guide is mixed with their BSDF there, so the bake stays unbiased"))
    warnings += clamp_warnings(scene, settings)
    if settings.bake_mode == "GUIDED" and float(settings.guide_fraction) >= 1.0:
        warnings.append("Guide fraction 1 never samples the cosine lobe: the bake is biased where "
                        "the optimal policy is zero; a value below 1 keeps it unbiased")
    plan = BakePlan(names=names, indices=indices, resolution=R, texels=texels, warnings=warnings,
                    memory_bytes=memory, texels_checked=bool(rasterise), resolutions=resolutions,
                    atlas=atlas)
    _leave_out(plan, skipped)
    return plan


def check_texels(scene, plan, progress=None):
    """Run the texel checks :func:`check_bake` left to later (``rasterise=False``) on ``plan``:
    every object is rasterised once, as a "texels" step of ``progress`` whose ``update`` (which
    raises ``Cancelled`` when the user asked to stop) runs before each object. Raises :class:`SceneError` for overlapping UVs and
    when no object covers a texel; leaves out (with a warning) objects that cover none while
    others do; fills ``plan.texels`` and returns ``plan``."""
    if not plan.texels_checked:
        if progress is not None:
            progress.begin("texels")
        resolutions = {i: plan.resolution_of(i) for i in plan.indices}
        plan.texels, skipped = _check_texels(scene, plan.names, plan.indices, resolutions, progress,
                                             atlas=plan.atlas)
        plan.texels_checked = True
        _leave_out(plan, skipped)
        if progress is not None:
            sizes = sorted({plan.resolution_of(i) for i in plan.indices})
            progress.end(f"{len(plan.names)} object(s) rasterised at "
                         f"{' / '.join(f'{r} x {r}' for r in sizes) or 'no size'}")
    return plan


def _leave_out(plan, skipped):
    """Drop the objects ``skipped`` ((name, reason) pairs: they cover no texel) from ``plan``
    with one warning naming them; the others are baked."""
    if not skipped:
        return
    gone = {name for name, _ in skipped}
    keep = [k for k, n in enumerate(plan.names) if n not in gone]
    plan.names = [plan.names[k] for k in keep]
    plan.indices = [plan.indices[k] for k in keep]
    plan.texel_warnings.append(
        "Not baked, their UV maps cover no texel centre of their lightmap: "
        + "; ".join(f"{n} ({why})" for n, why in skipped))


def _check_settings(settings, names):
    """The bake settings' errors; returns the resolution R."""
    mode = settings.bake_mode
    if mode not in BAKE_MODES:
        raise SceneError(f"Unknown bake mode {mode!r}: use one of {', '.join(BAKE_MODES)}")
    for setting, value, allowed in (("Bake Content", getattr(settings, "bake_content", "INDIRECT"), BAKE_CONTENTS),
                                    ("Output Format", getattr(settings, "output_format", "EXR_FLOAT"), OUTPUT_FORMATS),
                                    ("8-bit Copy", getattr(settings, "output_8bit", "NONE"), OUTPUT_8BIT)):
        if value not in allowed:
            raise SceneError(f"Unknown {setting} {value!r}: set LMDP > Bake > {setting} to one of {', '.join(allowed)}")
    R = int(settings.bake_resolution)
    if R < 1:
        raise SceneError(f"Bake resolution must be at least 1 pixel (got {R}): set LMDP > Bake > Resolution")
    if int(settings.bake_samples) < 1:
        raise SceneError(f"Bake samples must be at least 1 (got {settings.bake_samples}): set LMDP > Bake > Samples")
    if int(settings.max_bounces) < 1:
        raise SceneError(f"Max bounces must be at least 1 for indirect light (got {settings.max_bounces})")
    check_resolution_settings(settings)
    check_clamp(settings)
    if not names:
        raise SceneError("Select at least one mesh object to bake")
    return R


def _check_texels(scene, names, indices, resolutions, progress=None, atlas=False):
    """Rasterise every object once, object ``i`` at ``resolutions[i]``. Overlapping UVs are
    errors, and so is a bake in which no object covers a texel centre; objects that cover none
    while others do are returned to be left out. With ``atlas`` (one shared image) two objects
    covering the same texel are an error too. Returns ``(texels kept for the bake
    (:data:`TEXEL_CACHE_LIMIT`), [(name, reason)])``."""
    texels, kept = {}, 0
    empty, overlapping = [], []
    owner = {}   # atlas: which object covers each texel of the shared image (_atlas_clashes)
    shared = []
    for k, (n, i) in enumerate(zip(names, indices)):
        if progress is not None:
            progress.update(k / len(names), f"texels of {n}")
        R = int(resolutions[i])
        found = object_texels(scene, i, R)
        ts, _ = found
        if kept + len(ts) <= TEXEL_CACHE_LIMIT:
            texels[i] = found
            kept += len(ts)
        count, example = uv_overlaps(scene, i, R, found)
        if len(ts) == 0:
            empty.append((n, _why_no_texel(scene, i, R)))
        elif count:
            overlapping.append(f"{n} ({count} texels of its {R} x {R} lightmap, e.g. column {example[1]}, "
                               f"row {example[0]})")
        if atlas and len(ts):
            shared += _atlas_clashes(owner, names, n, ts)
    if empty and len(empty) == len(names):
        raise SceneError(f"The UV map of {'; '.join(f'{n} ({why})' for n, why in empty)} covers no "
                         "texel centre of its lightmap: nothing to bake")
    if overlapping:
        raise SceneError(f"Overlapping UVs on {'; '.join(overlapping)}: several faces share these "
                         "texels. Give each face its own area (LMDP > Bake > Create Lightmap UVs, or "
                         "UV > Lightmap Pack) and bake again")
    if shared:
        raise SceneError(f"The atlas's objects overlap in its {int(resolutions[indices[0]])} x "
                         f"{int(resolutions[indices[0]])} image: {'; '.join(shared)}. Pack their lightmap "
                         "UVs together (LMDP > Bake > Create Lightmap UVs with Atlas on) and bake again")
    return texels, empty


def _atlas_clashes(owner, names, name, ts):
    """Texels of ``ts`` (object ``name``) that another object of the atlas covers already:
    one message per such object. ``owner`` {'image': (R*R,) int32 image of the index into
    ``names`` of the first object covering each texel, -1: none} is updated in place."""
    R = ts.resolution
    if "image" not in owner:
        owner["image"] = np.full(R * R, -1, np.int32)
    image = owner["image"]
    flat = ts.flat_index
    first = image[flat]
    hit = first >= 0
    clashes = []
    for other in np.unique(first[hit]):
        where = flat[first == other]
        clashes.append(f"{name} and {names[other]} share {len(where)} texel(s), e.g. column "
                       f"{int(where[0] % R)}, row {int(where[0] // R)}")
    image[flat[~hit]] = names.index(name)
    return clashes


def _why_no_texel(scene, index, R):
    """Why an object's UV map covers no texel centre, with what to do."""
    uv = scene.triangle_uv[scene.triangle_object == index].reshape(-1, 2)
    if len(uv) and np.all((uv >= 0.0) & (uv <= 1.0)):
        return (f"its UV islands inside [0, 1] are all smaller than a texel at {R} x {R}: raise "
                "Resolution or scale the islands up (UV > Pack Islands)")
    return "UVs outside [0, 1] or degenerate: unwrap into the unit square"


def _check_uv_values(scene, names, indices, resolutions):
    """Objects whose UV maps hold non-finite or huge coordinates are errors: the faces could not
    be placed on the lightmap (Inf / NaN cover nothing, huge values a strip across the image)."""
    found = []
    R = max((int(resolutions[i]) for i in indices), default=1)
    for n, i in zip(names, indices):
        bad = bad_uv_faces(scene, i, int(resolutions[i]))
        if len(bad):
            uv = scene.triangle_uv[bad[0]]
            found.append(f"'{n}' ({len(bad)} triangle{'s' if len(bad) > 1 else ''}, e.g. one with UV "
                         f"{', '.join(f'({u:g}, {v:g})' for u, v in uv)})")
    if found:
        raise SceneError(f"The UV map of {'; '.join(found)} has non-finite or huge coordinates (Inf, "
                         f"NaN, or beyond ±{UV_TEXEL_LIMIT / R:g}, where a {R} x {R} lightmap cannot "
                         "place them): fix those UVs or unwrap again (UV > Lightmap Pack, or Smart UV "
                         "Project) and bake again")


def check_bake_memory(scene, names, indices, settings, resolutions=None):
    """The bake's estimated peak memory (bytes, ``memory.estimate_bake_bytes``) from an upper
    bound on each object's texels (``texels.texel_count_bound``: no rasterisation) at its
    resolution (``resolutions``: object index -> R, default ``bake_resolution``); raises
    :class:`BudgetError` when it exceeds ``settings.memory_budget_gb``."""
    from .driver import PATHS_PER_UNIT, bake_threads   # the driver imports this module
    sides = [int((resolutions or {}).get(i, settings.bake_resolution)) for i in indices]
    R = max(sides, default=int(settings.bake_resolution))
    counts = [texel_count_bound(scene.triangle_uv[(scene.triangle_object == i) & scene.usable_triangles()], r)
              for i, r in zip(indices, sides)]
    need = estimate_bake_bytes(counts, sides, int(settings.bake_samples), scene.n_triangles, bake_threads(),
                               PATHS_PER_UNIT)
    budget = settings.memory_budget_gb
    if budget is not None and need > float(budget) * 1024 ** 3:
        largest = int(np.argmax(counts))
        raise BudgetError(
            f"Baking {len(names)} object{'s' if len(names) > 1 else ''} at {R} x {R} would need "
            f"about {need / 1024 ** 3:.1f} GiB ('{names[largest]}' alone covers up to "
            f"{counts[largest]:,} texels), above the memory budget of {float(budget):g} GiB: lower "
            "LMDP > Bake > Resolution, bake fewer objects at once, or raise LMDP > Memory Budget "
            "(memory_budget_gb)")
    return need


_MODE_NAMES = {"FINAL_GATHER": "Final Gather", "RESIDUAL": "Residual"}


def _check_solution(scene, names, settings, lmdp, will_solve):
    """The stage-order and solution checks of the guided modes; returns their warnings."""
    warnings = []
    mode = settings.bake_mode
    if will_solve:
        if mode in ("FINAL_GATHER", "RESIDUAL") and settings.cost_mode != "PHYSICAL":
            raise SceneError(f"{_MODE_NAMES[mode]} reads the outgoing radiance z of the PHYSICAL cost mode: "
                             f"set Cost Mode to Physical (it is {settings.cost_mode}), or bake with "
                             "Guided or Unguided")
        return warnings
    if mode not in ("GUIDED", "FINAL_GATHER", "RESIDUAL"):
        return warnings
    if lmdp is None or lmdp.solution is None:
        raise StageOrderError(f"Solve first (LMDP panel > Solve): {mode} bakes are guided by "
                              "the optimal policy of the solved states; or use bake mode Unguided")
    same = scene_fingerprint(scene) == scene_fingerprint(lmdp.scene)
    if mode == "FINAL_GATHER":
        if lmdp.solution.cost_mode != "PHYSICAL":
            raise SceneError("Final Gather reads the outgoing radiance z of the PHYSICAL cost "
                             f"mode, but the solution was computed in {lmdp.solution.cost_mode} "
                             "mode: set Cost Mode to Physical and run the pipeline again")
        if not same:
            raise SceneError("The scene changed since the states were sampled: Final Gather would "
                             "read the old solution at the new surfaces. Run the pipeline again "
                             "(LMDP > Run All), or bake with Guided or Unguided")
    elif mode == "RESIDUAL":
        if lmdp.solution.cost_mode != "PHYSICAL":
            raise SceneError("Residual reads the outgoing radiance z of the PHYSICAL cost mode, but "
                             f"the solution was computed in {lmdp.solution.cost_mode} mode: set Cost "
                             "Mode to Physical and run the pipeline again, or bake with Unguided")
        if not same:
            warnings.append("The scene changed since the states were sampled: the bake traces the "
                            "current scene with the old solution as its control variate (still "
                            "unbiased, but noisier). Run the pipeline again for the best result")
    elif not same:
        warnings.append("The scene changed since the states were sampled: the bake traces the "
                        "current scene, guided by the old optimal policy (still unbiased, but "
                        "less effective). Run the pipeline again for the best guide")
    carried = set(np.asarray(lmdp.scene.object_names)[lmdp.states.point_object].tolist())
    unguided = [n for n in names if n not in carried]
    if unguided and mode != "RESIDUAL":     # RESIDUAL reads the states at the paths' hits only
        warnings.append(f"No states on {', '.join(unguided)}: their texels start with cosine "
                        "sampling (select them when sampling to guide them too)")
    return warnings


# ---- Whether a UV map can hold a lightmap -------------------------------------------------------------

#: A UV map whose covered texel centres are fewer than this share of the texels its UV area
#: holds is made of islands too small for the lightmap (most of them cover no texel centre).
MIN_COVERED_SHARE = 0.25
#: Tolerance of the unit square (UV units) before a coordinate counts as outside [0, 1].
UV_RANGE_TOLERANCE = 1e-6


def lightmap_uv_problems(scene, names, indices, resolutions, atlas=False):
    """{object name: why its UV map cannot hold its lightmap} for the objects ``names``
    (``indices``, object ``i`` at side ``resolutions[i]``): no UV map; non-finite or huge UVs;
    UVs outside [0, 1] (those faces get no texels); texel centres covered by two of its
    triangles (overlapping UVs, texel-level: ``TexelSet.overlap``); no texel centre covered, or
    fewer than :data:`MIN_COVERED_SHARE` of those its UV area holds (islands smaller than a
    texel); with ``atlas``, texels another object of the atlas covers. Objects not named are fine."""
    problems = {}
    owner, atlas_names = {}, list(names)
    for n, i in zip(names, indices):
        R = int(resolutions[i])
        if not scene.object_has_uv[i]:
            problems[n] = "it has no UV map"
            continue
        if len(bad_uv_faces(scene, i, R)):
            problems[n] = "its UV map has non-finite or huge coordinates"
            continue
        tris = np.flatnonzero((scene.triangle_object == i) & scene.usable_triangles())
        uv = scene.triangle_uv[tris]
        if np.any((uv < -UV_RANGE_TOLERANCE) | (uv > 1.0 + UV_RANGE_TOLERANCE)):
            problems[n] = "its UV map reaches outside [0, 1]"
            continue
        found = object_texels(scene, i, R)
        ts, _ = found
        count, _ = uv_overlaps(scene, i, R, found)
        if count:
            problems[n] = f"its UV map overlaps itself on {count} texel(s) of the {R} x {R} lightmap"
            continue
        e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        holds = 0.5 * float(np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()) * R * R
        if len(ts) == 0 or len(ts) < MIN_COVERED_SHARE * holds:
            problems[n] = (f"its UV islands are too small for a {R} x {R} lightmap ({len(ts)} texel "
                           f"centre(s) covered of about {holds:.0f} their area holds)")
            continue
        if atlas:
            clash = _atlas_clashes(owner, atlas_names, n, ts)
            if clash:
                problems[n] = "in the atlas, " + "; ".join(clash)
    return problems
