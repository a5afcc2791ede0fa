"""Where a bake's bias sits: the relative bias of an engine bake against Cycles' bake of the same
texels, per object and per block of the lightmap.

    .venv/bin/python bench/bias_map.py [SCENE] [OBJECT ...] [--modes FINAL_GATHER,UNGUIDED]
        [--points N] [--samples N] [--resolution R] [--blocks B] [--ref-samples N] [--seed S]

A mean bias over a whole lightmap can hide a leak in one corner. This bakes each object with
each mode and prints, for a B x B grid of blocks of its lightmap (top row = top of the UV
square), 100 (Σ bake / Σ reference − 1) over the texels that both cover, in luminance. A block
where Cycles finds (almost) no light and the bake does is printed as ``LEAK``: light where there
should be none, such as texels under a box standing on the floor that gathered the light of the
room (the bug that `gather.GatherField` now avoids). Blocks with too little reference light to
give a ratio are ``.``. UNGUIDED and GUIDED are unbiased, so their blocks show the noise level.

Below each map the bias is split by where the texels sit (``contact_classes``): *covered*
texels have another surface within 2 cm along their normal, or the back of one (under a box
standing on the floor: hidden from every view), the visible ones are grouped by their distance to other objects
(< 2 cm, 2-5 cm, farther: the contact shadows are the first group). A block of the map can mix
covered and visible texels; this split tells which of them carry its bias.

Cycles' reference (DIFFUSE / INDIRECT, adaptive sampling off, 8 bounces) is baked once per
(scene, object, resolution, samples) into ``bench/results/bias_map/`` and reused.
"""
import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import RESULTS, log  # noqa: E402

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: A block whose reference light is below this fraction of the brightest block's has no ratio.
DARK = 1e-3
#: A texel is covered when a surface lies within this distance (metres) along its normal.
COVERED = 0.02
#: Distance bands (metres) from other objects of the visible texels.
BANDS = (0.02, 0.05)
#: Directions in the texel's tangent plane along which the distance to other objects is probed,
#: and the height (metres) above the texel they start at (above the bumps of the HEAVY floor).
PROBES = 32
PROBE_HEIGHT = 0.004


def block_bias(values, reference, blocks):
    """Per-block relative bias of ``values`` against ``reference`` (both (R, R, 3) luminance
    images with NaN where not covered; R a multiple of ``blocks``): ``(bias (B, B), leak (B, B))``,
    bias = Σ values / Σ reference − 1 over the texels both cover (NaN where the reference light
    is below ``DARK`` of the brightest block's), leak = True where the reference is dark there
    but the values are not. Row 0 of the result is the top of the image (the last row of
    pixels, which Blender stores bottom-up)."""
    both = np.isfinite(values) & np.isfinite(reference)
    x = np.where(both, values, 0.0)
    y = np.where(both, reference, 0.0)
    size = x.shape[0] // blocks
    xs = x.reshape(blocks, size, blocks, size).sum(axis=(1, 3))[::-1]
    ys = y.reshape(blocks, size, blocks, size).sum(axis=(1, 3))[::-1]
    dark = ys <= DARK * max(ys.max(), 1e-300)
    bias = np.where(dark, np.nan, xs / np.where(dark, 1.0, ys) - 1.0)
    leak = dark & (xs > DARK * max(ys.max(), 1e-300))
    return bias, leak


def contact_classes(scene, texels, index, caster=None):
    """Per texel of object ``index``: 0 covered, 1, 2, 3 visible at a distance from other objects
    below ``BANDS[0]``, below ``BANDS[1]``, farther (module docstring; ray casts, metres;
    ``caster``: a ``RayCaster`` of ``scene`` to reuse)."""
    from lmdp_addon.model.hemisphere import tangent_frame
    from lmdp_addon.raycast import RayCaster
    caster = caster or RayCaster(scene)
    p = texels.position.astype(np.float64)
    n = texels.normal.astype(np.float64)
    tri, dist = caster.intersect(p + 0.001 * n, n)
    face_normals, _ = scene.triangle_geometry()
    inside = np.einsum("ij,ij->i", face_normals[np.maximum(tri, 0)], n) > 0   # a back face: in a solid
    covered = (tri >= 0) & ((dist < COVERED) | inside)
    frames = tangent_frame(n)
    origin = p + PROBE_HEIGHT * n
    nearest = np.full(len(p), np.inf)
    for a in np.linspace(0.0, 2.0 * np.pi, PROBES, endpoint=False):
        d = np.cos(a) * frames[:, 0] + np.sin(a) * frames[:, 1]
        tri, dist = caster.intersect(origin, d)
        other = (tri >= 0) & (scene.triangle_object[np.maximum(tri, 0)] != index)
        nearest = np.minimum(nearest, np.where(other, dist, np.inf))
    return np.where(covered, 0, 1 + np.searchsorted(np.asarray(BANDS), nearest, side="right"))


def format_contact(values, reference, classes):
    """One line: the bias of each class of :func:`contact_classes` (texels, bias)."""
    names = ("covered", f"visible < {100 * BANDS[0]:.0f} cm from another object",
             f"{100 * BANDS[0]:.0f}-{100 * BANDS[1]:.0f} cm", "farther")
    parts = []
    for c, name in enumerate(names):
        sel = classes == c
        if sel.any() and reference[sel].sum() > 0:
            parts.append(f"{name}: {int(sel.sum())} texels {100 * (values[sel].sum() / reference[sel].sum() - 1):+.1f} %")
    return "    by contact: " + "; ".join(parts)


def format_map(bias, leak):
    rows = []
    for b_row, l_row in zip(bias, leak):
        cells = ["LEAK" if l else ("   ." if not np.isfinite(b) else f"{100 * b:+4.0f}")
                 for b, l in zip(b_row, l_row)]
        rows.append("    " + " ".join(f"{c:>5}" for c in cells))
    return "\n".join(rows)


def luminance_image(rgb, covered):
    return np.where(covered, rgb[..., :3] @ LUMINANCE, np.nan)


def cycles_reference(kind, names, resolution, samples):
    """{name: (R, R, 4) Cycles bake} from the cache or baked now (one Blender session)."""
    cache = RESULTS / "bias_map"
    cache.mkdir(parents=True, exist_ok=True)
    paths = {n: cache / f"{kind.lower()}-{n}-{resolution}px-{samples}spp.npy" for n in names}
    missing = [n for n in names if not paths[n].exists()]
    if missing:
        from bench.blender_session import BlenderSession
        session = BlenderSession()
        try:
            session.load_scene(kind)
            for n in missing:
                log(f"Cycles reference of {n}: {resolution}px, {samples} samples ...")
                np.save(paths[n], session.bake(n, resolution, samples, seed=1, max_bounces=8))
        finally:
            session.close()
    return {n: np.load(paths[n]) for n in names}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", nargs="?", default="CORNELL_BOX")
    parser.add_argument("objects", nargs="*", default=["Floor"])
    parser.add_argument("--modes", default="FINAL_GATHER,UNGUIDED")
    parser.add_argument("--points", type=int, default=32768)
    parser.add_argument("--samples", type=int, default=256)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--blocks", type=int, default=8)
    parser.add_argument("--ref-samples", type=int, default=1024)
    parser.add_argument("--seed", type=int, default=0, help="the engine's seed (states, paths)")
    args = parser.parse_args(argv)
    if args.resolution % args.blocks:
        parser.error("--resolution must be a multiple of --blocks")
    references = cycles_reference(args.scene.upper(), args.objects, args.resolution, args.ref_samples)

    from lmdp_addon.bake import driver as baking
    from lmdp_addon.model import pipeline
    from lmdp_addon import demo_geometry as scenes
    from lmdp_addon.settings import Settings
    from lmdp_addon.raycast import RayCaster
    scene = scenes.build_scene_arrays(args.scene)
    caster = RayCaster(scene)
    classes = {}   # per object: the same texels in every mode
    for mode in args.modes.split(","):
        settings = replace(Settings(), point_count=args.points, bake_mode=mode, bake_samples=args.samples,
                           bake_margin=0, bake_resolution=args.resolution, seed=args.seed)
        lmdp = pipeline.run_all(scene, settings) if mode != "UNGUIDED" else None
        for ob in baking.bake(scene, args.objects, settings, lmdp).objects:
            ref = references[ob.name]
            img = ob.texels.to_image(ob.value.astype(np.float32))
            values = luminance_image(img, np.isfinite(img[..., 0]))
            reference = luminance_image(ref, ref[..., 3] != -1)   # Cycles leaves uncovered texels alone
            both = np.isfinite(values) & np.isfinite(reference)
            total = values[both].sum() / reference[both].sum() - 1.0
            states = "" if lmdp is None else f"{args.points} points, "
            print(f"{mode} {ob.name} ({states}{args.samples} samples): bias {100 * total:+.2f} %")
            print(format_map(*block_bias(values, reference, args.blocks)))
            ts = ob.texels
            if ob.name not in classes:
                classes[ob.name] = contact_classes(scene, ts, scene.object_names.index(ob.name), caster)
            print(format_contact(values[ts.row, ts.col], reference[ts.row, ts.col], classes[ob.name]))


if __name__ == "__main__":
    main()
