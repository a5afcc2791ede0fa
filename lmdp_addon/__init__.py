"""LMDP Light Transport engine: light transport as a linearly-solvable MDP (no bpy here).

Stages (thesis chapter 3): scene arrays -> states (3.1.1) -> passive dynamics (3.1.2) ->
state costs (3.1.3) -> desirability z (2.22, 3.1.4) -> optimal policy u* (2.23) ->
guided path tracing / lightmap baking (3.1.5).
"""
