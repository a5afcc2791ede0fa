"""The light-transport LMDP (thesis chapter 3): states, passive dynamics, costs, solvers, policy."""
