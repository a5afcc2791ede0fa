"""The light-transport LMDP (thesis chapter 3), one module per step:

* ``hemisphere``: equal-area hemisphere warps and strata (Figure 2);
* ``states``: the state space, surface points with stratified hemispheres (3.1.1);
* ``unknowns``: the solve's unknowns, one per Lambertian point and one per (point, outgoing
  stratum) on glossy points;
* ``dynamics``: the passive dynamics by ray casting (3.1.2, eq. 3.1), built from
  ``patterns`` (the stratum and next-event ray patterns), ``hits`` (hit classification: which
  next state a ray lands in) and ``locator`` (the nearest state point of a hit; buried points);
* ``costs``: state costs and the first-exit LMDP (3.1.3);
* ``solvers``: the desirability z (2.22, 3.1.4) and the cost-to-go J (2.24);
* ``policy``: the optimal policy u* over next states and over strata (2.23);
* ``pipeline``: the stages as one call each, on ``Settings``;
* ``export``: the problem and its solution as a self-describing ``.npz``.
"""
