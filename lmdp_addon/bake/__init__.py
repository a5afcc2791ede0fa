"""Lightmap baking by path tracing, guided by the solved LMDP (thesis 3.1.5)."""
