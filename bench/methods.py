"""The bake methods compared by the speed-against-error benchmark, as pluggable entries.

A method is an object with

* ``name`` (unique label of its curve), ``family`` ('Cycles', 'UNGUIDED', 'GUIDED',
  'FINAL_GATHER'), ``ladder`` (the sample counts it is run at), ``describe()`` (its settings);
* ``prepare(case, seed) -> Prepared``: the precompute, timed per stage (nothing for Cycles and
  UNGUIDED; the LMDP sample + build + solve for GUIDED and FINAL_GATHER);
* ``bake(case, prepared, samples, seed) -> BakeRun``: one bake of the receiver, returning the
  texel values of ``case.rows, case.cols`` and the wall time of the call.

``case`` is a :class:`speed_error.BakeCase` (scene, receiver, resolution, bounces, texels, and the
Blender session for Cycles). Adding a method means adding an entry to ``speed_error.method_plan``.

What is timed (``time.perf_counter`` around the calls, nothing else):

* Cycles: ``operators.adapters.demo_scenes.bake_cycles`` = ``bpy.ops.object.bake`` of the receiver (scene
  sync, BVH, shading, readback) plus creating and removing its scratch image: what a user waits
  for when baking.
* LMDP precompute: ``pipeline.run_sample``, ``run_build``, ``run_solve`` (the engine functions the
  ``lmdp.sample_states`` / ``build_dynamics`` / ``solve`` operators call), each separately.
* LMDP bake: ``baking.bake`` (what ``lmdp.bake`` calls): input checks, the ray caster's BVH (GUIDED
  and FINAL_GATHER reuse the build's: it was timed in the precompute), the guide (state locator
  and u*), texel rasterisation, tracing and the margin.
The Blender-side copying of engine results into images is not timed on either side (Cycles'
readback of its own image is, through ``bake_cycles``).
"""
from dataclasses import dataclass, field, replace

import numpy as np

from .common import Stopwatch


@dataclass
class Prepared:
    state: object = None
    seconds: dict = field(default_factory=dict)   #: stage -> wall seconds

    @property
    def total(self):
        return float(sum(self.seconds.values()))


@dataclass
class BakeRun:
    values: np.ndarray          #: (n, 3) at the case's scored texels
    seconds: float              #: wall time of the bake call
    info: dict = field(default_factory=dict)


class CyclesBake:
    """Cycles' own bake: DIFFUSE with pass filter INDIRECT, adaptive sampling off; ``guiding``:
    with Cycles' path guiding (Open PGL, ``scene.cycles.use_guiding``) on."""

    family = "Cycles"

    def __init__(self, ladder, name="Cycles", guiding=False):
        self.name = name
        self.ladder = tuple(int(s) for s in ladder)
        self.guiding = bool(guiding)

    def describe(self):
        return {"bake": "bpy.ops.object.bake(type='DIFFUSE', pass_filter={'INDIRECT'})",
                "adaptive_sampling": False, "denoising": False, "margin": 0, "use_guiding": self.guiding}

    def prepare(self, case, seed):
        return Prepared()

    def bake(self, case, prepared, samples, seed):
        with Stopwatch() as sw:
            image = case.blender.bake(case.receiver, case.resolution, samples, seed, case.bounces,
                                      guiding=self.guiding)
        return BakeRun(values=image[case.rows, case.cols, :3].astype(np.float64), seconds=sw.seconds,
                       info={"covered": int(np.count_nonzero(image[..., 3] >= 0))})


class LMDPBake:
    """This project's bake (``lmdp_addon.bake.driver.bake``) in one ``bake_mode``, with the LMDP
    precompute of ``settings`` for GUIDED, FINAL_GATHER and RESIDUAL. AUTO solves inside the
    timed bake when its pilot asks for the solution (``pipeline.run_all``, as the Bake operator
    does), so its wall time includes that precompute."""

    def __init__(self, mode, ladder, name=None, **settings):
        self.family = mode
        self.ladder = tuple(int(s) for s in ladder)
        self.overrides = dict(settings)
        self.name = name or mode

    def settings(self, case, samples=1, seed=0):
        from lmdp_addon.settings import Settings
        base = Settings()
        return replace(base, **self.overrides, bake_mode=self.family, bake_resolution=case.resolution,
                       bake_samples=int(samples), max_bounces=case.bounces, bake_margin=0, seed=int(seed),
                       output_dir="")

    def describe(self):
        from lmdp_addon.settings import Settings
        s = replace(Settings(), **self.overrides, bake_mode=self.family)
        keys = ["bake_mode", "guide_fraction"]
        if self.family != "UNGUIDED":
            keys += ["point_count", "strata_u", "strata_v", "rays_per_stratum", "light_samples", "cost_mode",
                     "lambda_scale", "solver", "tolerance"]
        return {k: getattr(s, k) for k in keys}

    def prepare(self, case, seed):
        if self.family in ("UNGUIDED", "AUTO"):
            return Prepared()
        from lmdp_addon.model import pipeline
        settings = self.settings(case, seed=seed)
        result = pipeline.LMDPResult(scene=case.scene)
        seconds = {}
        with Stopwatch() as sw:
            result.states, _ = pipeline.run_sample(case.scene, settings)
        seconds["sample"] = sw.seconds
        with Stopwatch() as sw:
            result.dynamics, _ = pipeline.run_build(case.scene, result.states, settings)
        seconds["build"] = sw.seconds
        with Stopwatch() as sw:
            result.lmdp, result.solution, _ = pipeline.run_solve(case.scene, result.states, result.dynamics, settings)
        seconds["solve"] = sw.seconds
        return Prepared(state=result, seconds=seconds)

    def bake(self, case, prepared, samples, seed):
        from lmdp_addon.bake import driver as baking
        from lmdp_addon.model import pipeline
        settings = self.settings(case, samples, seed)
        solve = (lambda: pipeline.run_all(case.scene, settings, check=False)) if self.family == "AUTO" else None
        with Stopwatch() as sw:
            result = baking.bake(case.scene, [case.receiver], settings, prepared.state, solve=solve)
        ob = result.objects[0]
        image = ob.texels.to_image(ob.value.astype(np.float32))
        rays = int(ob.stats.total_rays)
        return BakeRun(values=image[case.rows, case.cols].astype(np.float64), seconds=sw.seconds,
                       info={"rays": rays, "texels": int(ob.n_texels),
                             "bake_seconds": {k: float(v) for k, v in result.seconds.items()},
                             **({"auto": result.auto.as_dict()} if result.auto is not None else {})})


def lmdp_bake_available():
    """``(True, '')`` when the engine's bake exists, else ``(False, reason)``."""
    try:
        from lmdp_addon.bake import driver as baking  # noqa: F401
        return True, ""
    except ImportError as exc:
        return False, f"lmdp_addon.bake.driver is not importable ({exc})"
