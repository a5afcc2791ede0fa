"""LMDP Light Transport engine: light transport as a linearly-solvable MDP (no bpy here).

Stages (thesis chapter 3): scene arrays -> states (3.1.1) -> passive dynamics (3.1.2) ->
state costs (3.1.3) -> desirability z (2.22, 3.1.4) -> optimal policy u* (2.23) ->
guided path tracing / lightmap baking (3.1.5).

Subpackages: :mod:`~lmdp_addon.model` (the LMDP: states to policy, and the stage calls in
``model.pipeline``), :mod:`~lmdp_addon.bake` (the lightmap baker), :mod:`~lmdp_addon.display`
(what the viewport shows of a solution). Shared modules:

* ``scene_arrays``: the scene as flat triangle arrays (``SceneArrays``), the engine's only input;
* ``demo_geometry``: the built-in scenes as parts (``demo_uv``: their UV charts);
* ``raycast``: batched closest-hit and occlusion queries (embree);
* ``lights``: light sampling, points on the emitters (``EmitterSampler``);
* ``sampling``: low-discrepancy sequences and warps shared by the stages;
* ``settings``, ``progress``, ``errors``: the settings of every stage, progress and
  cancellation, typed errors with messages for the user.
"""
