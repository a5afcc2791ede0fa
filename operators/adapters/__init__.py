"""bpy data <-> engine arrays: ``extract`` (scene -> SceneArrays), ``display_targets`` /
``display_data`` / ``display_objects`` / ``viewport`` (showing z and u*), ``lightmaps`` (baked
images and files), ``materials`` (lightmap hook-up), ``demo_scenes`` (built-in scenes, Cycles
reference bakes)."""
