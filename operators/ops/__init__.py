"""The operators: stages, bake, display, demo scenes (thin: settings -> engine -> results)."""
