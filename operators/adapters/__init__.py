"""bpy data <-> engine arrays: scene extraction, display data, demo scenes, lightmap images."""
