"""The lightmap size of each baked object: ``bake_resolution`` for all (``FIXED``), or from a
texel density (``DENSITY``).

With ``resolution_mode = 'DENSITY'`` an object whose surface has world-space area A (m²) and
whose UV triangles cover the fraction a of the unit square (the UV map's packing) gets the side

    R = texel_density · sqrt(A / a)                                  (texels per metre)

so that the a R² texels its islands cover fall on A m² of surface at ``texel_density``² texels
per m²; R is rounded up (to a power of two with ``power_of_two``) and clamped to
[``min_resolution``, ``max_resolution``]. The objects of an atlas share one image: A and a are
summed over them (their islands are packed into one unit square).
"""
import numpy as np

from ..errors import SceneError
from ..settings import RESOLUTION_MODES


def surface_areas(scene, index):
    """``(world area m², UV area (fraction of the unit square))`` of object ``index``'s usable
    triangles."""
    tris = np.flatnonzero((scene.triangle_object == index) & scene.usable_triangles())
    world = scene.triangle_geometry()[1][tris]
    uv = scene.triangle_uv[tris].astype(np.float64)
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    with np.errstate(invalid="ignore"):
        flat = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    return float(np.sum(world[np.isfinite(world)])), float(np.sum(flat[np.isfinite(flat)]))


def density_resolution(world_area, uv_area, settings):
    """The side R of a lightmap at ``settings.texel_density`` for a surface of ``world_area`` m²
    whose UV islands cover ``uv_area`` of the unit square (module docstring)."""
    lo, hi = int(settings.min_resolution), int(settings.max_resolution)
    if world_area <= 0 or uv_area <= 0:
        return lo
    side = float(settings.texel_density) * np.sqrt(world_area / min(uv_area, 1.0))
    R = max(1, int(np.ceil(side - 1e-9)))
    if settings.power_of_two:
        R = 1 << int(np.ceil(np.log2(R)))
    return int(min(max(R, lo), hi))


def check_resolution_settings(settings):
    """Raise ``SceneError`` for a resolution mode or density bounds the bake cannot use."""
    mode = settings.resolution_mode
    if mode not in RESOLUTION_MODES:
        raise SceneError(f"Unknown resolution mode {mode!r}: use one of {', '.join(RESOLUTION_MODES)}")
    if mode != "DENSITY":
        return
    if not float(settings.texel_density) > 0:
        raise SceneError(f"Texel density must be above 0 texels per metre (got {settings.texel_density}): "
                         "set LMDP > Bake > Texel Density")
    lo, hi = int(settings.min_resolution), int(settings.max_resolution)
    if lo < 1 or hi < lo:
        raise SceneError(f"The lightmap size range [{lo}, {hi}] is empty or below 1 pixel: set LMDP > Bake > "
                         "Min / Max Resolution with 1 <= Min <= Max")


def object_resolutions(scene, indices, settings, atlas=False):
    """{object index: lightmap side R} of the objects ``indices`` (module docstring); with
    ``atlas`` they all get the one side of their shared image."""
    if settings.resolution_mode != "DENSITY":
        return {i: int(settings.bake_resolution) for i in indices}
    areas = {i: surface_areas(scene, i) for i in indices}
    if atlas:
        R = density_resolution(sum(a for a, _ in areas.values()), sum(u for _, u in areas.values()), settings)
        return {i: R for i in indices}
    return {i: density_resolution(*areas[i], settings) for i in indices}
