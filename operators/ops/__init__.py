"""The operators, thin (settings -> engine -> results): ``pipeline`` (Sample, Build, Solve, Run
All, Export), ``bake``, ``display`` (Show / View Desirability, Clear), ``policy`` (Show Policy,
Probe), ``scenes`` (Add > LMDP Demo Scene). No operator module imports another."""
