"""The results of a bake: one :class:`ObjectBake` lightmap per object in a :class:`BakeResult`,
and the plain dict of ``bake_stats.json`` (:meth:`BakeResult.stats`)."""
from dataclasses import dataclass, field

import numpy as np

from ..settings import LightPaths
from .tracer import TraceStats

#: Suffix of the images the add-on writes.
IMAGE_SUFFIX = "_lmdp_indirect"
#: Added to the image (and file) name of the raw lightmap a denoised bake keeps.
RAW_SUFFIX = "_raw"
#: Name of the shared lightmap of an atlas bake (``Settings.atlas``); its image is
#: ``ATLAS_NAME + IMAGE_SUFFIX``.
ATLAS_NAME = "LMDP Atlas"


@dataclass
class ObjectBake:
    """The lightmap of one object.

    name            object name; the image is ``name + IMAGE_SUFFIX``
    texels          :class:`~lmdp_addon.bake.texels.TexelSet` (covered texels, Cycles' mapping)
    triangles       (T_o,) the scene triangle of each of the object's local triangle indices
    value           (n, 3) float32 estimate per covered texel of the bake content (``content``:
                    E_ind/π, (E_dir + E_ind)/π, either times ρ; W / sr m²), as path traced
    standard_error  (n, 3) float32 standard error of ``value`` from the batch means (NaN for 1 batch)
    image           (R, R, 4) float32 RGBA, margin filled, alpha 1 where filled; row 0 = bottom
                    (of an atlas member: the atlas's shared image)
    samples         paths per texel; batches: independent batches they were split into
    stats           :class:`~lmdp_addon.bake.tracer.TraceStats`
    seconds         wall time of this object's bake
    raw_image       (R, R, 4) the path-traced image when ``image`` was denoised, else None
    denoised_value  (n, 3) the denoised texels when ``image`` was denoised, else None
    batch_means     (B, n, 3) float32 each independent batch's texel means (None: one batch, or
                    a bake larger than ``memory.BATCH_MEANS_BYTES``): :meth:`mean_and_error`
    """

    name: str
    texels: object
    triangles: np.ndarray
    value: np.ndarray
    standard_error: np.ndarray
    image: np.ndarray
    samples: int
    batches: int
    stats: TraceStats
    seconds: float
    raw_image: np.ndarray = None
    denoised_value: np.ndarray = None
    atlas: str = ""                 #: the atlas whose shared image holds this lightmap ('' = its own)
    batch_means: np.ndarray = None

    def mean_and_error(self, texels=None):
        """``(mean, standard error)`` (3,) of the mean value of the texels ``texels`` (a mask or
        indices; None: all). The error comes from the batches' means of the region, which are
        independent: it holds whether or not texels share paths (path reuse shares first bounces
        within a batch, ``reuse``). Without ``batch_means`` it assumes independent texels, which
        only holds without path reuse (``stats.shared_hits`` 0)."""
        sel = slice(None) if texels is None else texels
        value = self.value[sel].astype(np.float64)
        mean = value.mean(axis=0)
        if self.batch_means is not None:
            region = self.batch_means[:, sel].astype(np.float64).mean(axis=1)        # (B, 3)
            B = len(region)
            return mean, np.sqrt(((region - region.mean(axis=0)) ** 2).sum(axis=0) / (B - 1) / B)
        if self.stats.shared_hits:
            raise ValueError(f"{self.name}: the error of a region's mean needs the batch means of a bake "
                             "with path reuse (its texels share paths)")
        se = self.standard_error[sel].astype(np.float64)
        return mean, np.sqrt((se ** 2).sum(axis=0)) / len(value)

    @property
    def image_name(self):
        return (self.atlas or self.name) + IMAGE_SUFFIX

    @property
    def raw_image_name(self):
        """The image that keeps the path-traced lightmap of a denoised bake."""
        return self.image_name + RAW_SUFFIX

    @property
    def n_texels(self):
        return len(self.texels)

    @property
    def resolution(self):
        return self.texels.resolution


@dataclass
class AtlasBake:
    """The shared lightmap of several objects (``Settings.atlas``): ``image`` (R, R, 4) holds
    each member's texels in its own region (``driver.compose_atlas``)."""

    name: str
    members: list                   #: names of the objects whose texels it holds
    image: np.ndarray

    @property
    def image_name(self):
        return self.name + IMAGE_SUFFIX

    @property
    def resolution(self):
        return self.image.shape[0]


@dataclass
class BakeResult:
    """Lightmaps of the baked objects plus what produced them (``bake_stats.json``)."""

    mode: str
    objects: list
    settings: dict
    seconds: dict = field(default_factory=dict)   #: stage -> wall time: sample, build, solve, bake
    warnings: list = field(default_factory=list)
    guide_info: dict = field(default_factory=dict)
    #: ``LightPaths.as_dict()`` of the path length used (empty: ``settings['max_bounces']``, CUSTOM)
    light_paths: dict = field(default_factory=dict)
    atlases: list = field(default_factory=list)   #: :class:`AtlasBake` of an atlas bake
    #: AUTO: the ``auto.AutoChoice`` of its parts (None: another mode)
    auto: object = None
    #: World portals (``portals.Portals.info`` and the probe's seconds; empty: not used)
    portals: dict = field(default_factory=dict)

    def outputs(self):
        """The images to write: each object that has its own (``ObjectBake``), then each atlas
        (``AtlasBake``); both have ``name``, ``image_name``, ``resolution`` and ``image``."""
        return [o for o in self.objects if not o.atlas] + list(self.atlases)

    def output_of(self, name):
        """The name of the output (object or atlas) whose image holds object ``name``'s lightmap."""
        return self.object(name).atlas or name

    @property
    def n_texels(self):
        return sum(o.n_texels for o in self.objects)

    def object(self, name):
        for o in self.objects:
            if o.name == name:
                return o
        raise KeyError(name)

    def summary(self):
        rays = sum(o.stats.total_rays for o in self.objects)
        secs = sum(o.seconds for o in self.objects)
        return (f"{self.mode} bake of {len(self.objects)} object(s), {self.n_texels} texels x "
                f"{self.settings.get('bake_samples')} samples, {rays} rays in {secs:.2f} s")

    def stats(self):
        """Plain dict for ``bake_stats.json``."""
        objects = {}
        for o in self.objects:
            rays = o.stats.total_rays
            objects[o.name] = {
                "image": o.image_name,
                "resolution": o.resolution,
                "atlas": o.atlas or None,
                "texels": o.n_texels,
                "samples": o.samples,
                "batches": o.batches,
                "paths": o.stats.paths,
                "rays": rays,
                "closest_hit_rays": o.stats.rays,
                "shadow_rays": o.stats.shadow_rays,
                "rays_per_second": rays / o.seconds if o.seconds > 0 else None,
                "trace": o.stats.as_dict(),
                "mean": [float(x) for x in o.value.mean(axis=0)] if o.n_texels else [0.0, 0.0, 0.0],
                "mean_relative_standard_error": _relative_error(o),
                "denoised": o.raw_image is not None,
                "seconds": {**{k: v for k, v in self.seconds.items() if k != "bake"}, "bake": o.seconds},
            }
        return {
            "mode": self.mode,
            "settings": dict(self.settings),
            "seconds": dict(self.seconds),
            "guide": dict(self.guide_info),
            "light_paths": dict(self.light_paths) or LightPaths.custom(
                self.settings.get("max_bounces", 0), self.settings.get("clamp_direct", 0.0),
                self.settings.get("clamp_indirect", 0.0)).as_dict(),
            "objects": objects,
            "atlases": {a.name: {"image": a.image_name, "resolution": a.resolution, "objects": list(a.members)}
                        for a in self.atlases},
            "warnings": list(self.warnings),
            **({"auto": self.auto.as_dict()} if self.auto is not None else {}),
            **({"portals": dict(self.portals)} if self.portals else {}),
        }


def _relative_error(o):
    """RMS standard error over the texels divided by the mean value (luminance-free: all channels)."""
    if o.n_texels == 0 or not np.all(np.isfinite(o.standard_error)):
        return None
    mean = float(o.value.mean())
    return float(np.sqrt(np.mean(o.standard_error.astype(np.float64) ** 2)) / mean) if mean > 0 else None
