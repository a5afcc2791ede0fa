"""Where a bake's bias sits: the relative bias of an engine bake against Cycles' bake of the same
texels, per object and per block of the lightmap.

    .venv/bin/python bench/bias_map.py [SCENE] [OBJECT ...] [--modes FINAL_GATHER,UNGUIDED]
        [--points N] [--samples N] [--resolution R] [--blocks B] [--ref-samples N] [--seed S]

A mean bias over a whole lightmap can hide a leak in one corner. This bakes each object with
each mode and prints, for a B x B grid of blocks of its lightmap (top row = top of the UV
square), 100 (Σ bake / Σ reference − 1) over the texels that both cover, in luminance. A block
where Cycles finds (almost) no light and the bake does is printed as ``LEAK``: light where there
should be none, such as texels under a box standing on the floor that gathered the light of the
room (the bug that `tracer.GatherField` now avoids). Blocks with too little reference light to
give a ratio are ``.``. UNGUIDED and GUIDED are unbiased, so their blocks show the noise level.

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

    from lmdp_addon import baking, pipeline, scenes
    from lmdp_addon.settings import Settings
    scene = scenes.build_scene_arrays(args.scene)
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


if __name__ == "__main__":
    main()
