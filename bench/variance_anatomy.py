"""Where the bake's variance comes from: per-sample relative variance of the indirect light at
random points of a receiver, by path length, and with the scene's mesh light made one-sided.

    .venv/bin/python bench/variance_anatomy.py [SCENE RECEIVER] [--points N] [--paths M] [--guided]

Prints, for UNGUIDED paths of 1, 2 and 8 bounces, the mean of the luminance of I = E_ind/π over
the points and its variance per path relative to the squared mean (the number of samples per
texel needed for a relative RMSE of 1 is this variance), and the share of that variance the
largest 0.1 % of the paths carry (a heavy tail: rare paths of large value); then the same at 8 bounces with the
emitters made one-sided (front side only, as an area light): the difference is what the light's
back side, hanging 5 mm below the ceiling in the built-in scenes, contributes to the mean and to
the variance. With ``--guided`` also GUIDED paths of 8 bounces, guided by the LMDP of the add-on's
default settings (its own states, 2048 of them, sampled on the whole scene), with either light:
how much of the variance the guide removes once the gap is gone. Engine only (no Blender); a few
seconds per scene.
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lmdp_addon.bake.guide import build_guide  # noqa: E402
from lmdp_addon.model import pipeline  # noqa: E402
from lmdp_addon import demo_geometry as scenes  # noqa: E402
from lmdp_addon.settings import Settings  # noqa: E402
from lmdp_addon.bake.tracer import IndirectTracer  # noqa: E402

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: The tail reported: the share of the variance carried by this fraction of the paths.
TAIL = 1e-3


def receiver_points(scene, name, n, rng):
    """``n`` uniform points on the upward-facing triangles of object ``name`` and their normals."""
    obj = scene.object_names.index(name)
    normals, areas = scene.triangle_geometry()
    tri = np.flatnonzero((scene.triangle_object == obj) & (normals[:, 2] > 0.5) & (areas > 0))
    pick = tri[rng.choice(len(tri), n, p=areas[tri] / areas[tri].sum())]
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    c = scene.corners()[pick]
    return c[:, 0] + u[:, None] * (c[:, 1] - c[:, 0]) + v[:, None] * (c[:, 2] - c[:, 0]), normals[pick]


def relative_variance(scene, points, normals, paths, bounces, rng, tail=None, guide=None, obj=-1):
    """(mean, variance per path / mean²) of the luminance of UNGUIDED estimates at ``points``
    (GUIDED with a ``guide.StateGuide`` ``guide``; ``obj``: the receiver's object index);
    with ``tail`` = q also the share of the variance that the largest fraction q of the paths
    carry (squared deviations from their point's mean)."""
    n = len(points)
    tracer = IndirectTracer(scene, "GUIDED" if guide is not None else "UNGUIDED", max_bounces=bounces,
                            guide=guide)
    p, nn = np.repeat(points, paths, axis=0), np.repeat(normals, paths, axis=0)
    states = np.full(n * paths, -1) if guide is None else guide.states_at(p, nn, np.full(n * paths, obj))
    values, _ = tracer.trace(p, nn, states, rng.random((n * paths, 2)), rng.random(n * paths), rng)
    lum = (values.astype(np.float64) @ LUMINANCE).reshape(n, paths)
    mean = lum.mean()
    result = (mean, lum.var(axis=1).mean() / mean ** 2)
    if tail is None:
        return result
    dev = np.sort(((lum - lum.mean(axis=1, keepdims=True)) ** 2).ravel())[::-1]
    top = max(1, int(round(tail * dev.size)))
    return result + (dev[:top].sum() / dev.sum(),)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cases", nargs="*", default=["CORNELL_BOX", "Floor", "NARROW_OPENING", "RoomAFloor"],
                        help="pairs of SCENE RECEIVER")
    parser.add_argument("--points", type=int, default=2048)
    parser.add_argument("--paths", type=int, default=256)
    parser.add_argument("--guided", action="store_true", help="also GUIDED paths (module docstring)")
    args = parser.parse_args(argv)
    for kind, name in zip(args.cases[::2], args.cases[1::2]):
        scene = scenes.build_scene_arrays(kind)
        rng = np.random.default_rng(0)
        points, normals = receiver_points(scene, name, args.points, rng)
        print(f"{kind} / {name}: {args.points} points x {args.paths} paths (UNGUIDED)")
        for bounces in (1, 2, 8):
            mean, rv, share = relative_variance(scene, points, normals, args.paths, bounces, rng, tail=TAIL)
            print(_line(f"up to {bounces} bounce(s)", mean, rv, share))
        if args.guided:
            print(_guided_line(scene, name, points, normals, args.paths, rng, rv))
        scene.triangle_emission_two_sided = np.zeros_like(scene.triangle_emission_two_sided)
        mean, rv, share = relative_variance(scene, points, normals, args.paths, 8, rng, tail=TAIL)
        print(_line("one-sided light, 8 bounces", mean, rv, share))
        if args.guided:
            print(_guided_line(scene, name, points, normals, args.paths, rng, rv, "one-sided light, "))


def _guided_line(scene, name, points, normals, paths, rng, unguided, light=""):
    """The GUIDED counterpart of the last UNGUIDED line (8 bounces), as one printed line."""
    settings = Settings()
    lmdp = pipeline.run_all(scene, settings)
    guide = build_guide(scene, lmdp)
    mean, rv, share = relative_variance(scene, points, normals, paths, 8, rng, tail=TAIL, guide=guide,
                                        obj=scene.object_names.index(name))
    return _line(f"{light}GUIDED ({settings.point_count} states), 8 bounces", mean, rv, share,
                 f" ({rv / unguided:.2f} x UNGUIDED's)")


def _line(label, mean, rv, share, note=""):
    """One printed result: the mean, the variance per path / mean² (and ``note``), the tail share."""
    return (f"  {label}: mean {mean:.4f}, variance per path / mean^2 {rv:7.2f}{note}, "
            f"{100 * TAIL:g} % of the paths carry {100 * share:.0f} % of it")


if __name__ == "__main__":
    main()
