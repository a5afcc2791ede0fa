"""Lightmap baking by path tracing, guided by the solved LMDP (thesis 3.1.5).

driver   the bake: ``bake`` (one call per bake), ``bake_object``, ``make_tracer``, work units
checks   every check of a bake, run once: ``check_bake -> BakePlan`` (texels, warnings, memory)
memory   the bake's memory estimate ``estimate_bake_bytes`` (checked against ``memory_budget_gb``)
results  ``ObjectBake``, ``BakeResult`` (``bake_stats.json``), ``IMAGE_SUFFIX``
texels   texel rasterisation (Cycles' mapping of a UV map), footprint samples, margin dilation
tracer   the wavefront path tracer ``IndirectTracer`` and its ``TraceStats``
guide    the guide: ``StateGuide``, ``neighbour_average``, ``build_guide``, direction sampling
fine_guide  GUIDED's table: the light arriving at each state through G x G cells (``build_fine_guide``)
gather   final gather: ``GatherField``, ``build_gather``, ``direct_after_one_bounce``

Light sampling (shared with the build) is ``lmdp_addon/lights.py``; the shared sequences and
float32 warps are ``lmdp_addon/sampling.py``.
"""
