"""Headless Blender (the PyPI ``bpy`` of the venv) with this checkout loaded as an extension, for
Cycles' reference bakes.

The extension is loaded the way Blender loads extensions (``scripts/lmdp_extension.py``: a
temporary extension repository holding a symlink to the checkout), with ``BLENDER_USER_RESOURCES``
pointing at a temporary directory so that the user's own Blender setup is never read or written.
Scenes come from ``operators.adapters.demo_scenes.build_demo_scene`` (the same parts as
``lmdp_addon.demo_geometry``) and bakes from ``operators.adapters.demo_scenes.bake_cycles``
(``bpy.ops.object.bake(type='DIFFUSE', pass_filter={'INDIRECT'})`` into a scratch float image,
adaptive sampling and indirect clamping off, user state restored).
"""
import importlib
import os
import shutil
import sys
import tempfile

from .common import ROOT

#: Value the scratch image is filled with before a bake: Cycles leaves uncovered pixels alone.
SENTINEL = -1.0


class BlenderSession:
    """One bpy session with the extension enabled; ``close()`` removes everything it made."""

    def __init__(self):
        if "bpy" in sys.modules:
            raise RuntimeError("bpy was imported before the benchmark could isolate its user resources")
        self._tmp = tempfile.mkdtemp(prefix="lmdp_bench_blender_")
        # Read once, when bpy is imported: the user's preferences and extensions stay untouched.
        os.environ["BLENDER_USER_RESOURCES"] = os.path.join(self._tmp, "user")
        scripts = str(ROOT / "scripts")
        if scripts not in sys.path:
            sys.path.insert(0, scripts)
        import bpy
        import lmdp_extension
        self.bpy = bpy
        self._ext = lmdp_extension
        self.module, self._repo = lmdp_extension.register_checkout(
            ROOT, os.path.join(self._tmp, "repo"), repo_module="lmdp_bench", repo_name="LMDP benchmark")
        self.demo = importlib.import_module(f"{self.module}.operators.adapters.demo_scenes")
        self.kind = None

    @property
    def version(self):
        return self.bpy.app.version_string

    @property
    def cycles_threads(self):
        """Render threads Cycles uses (``render.threads``: auto-detected unless set)."""
        render = self.bpy.context.scene.render
        return f"{render.threads} ({render.threads_mode.lower()})"

    def load_scene(self, kind):
        """An empty file, then the built-in scene ``kind`` (meshes, materials, world, Cycles)."""
        bpy = self.bpy
        bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
        self.demo.build_demo_scene(kind, bpy.context)
        self.kind = kind

    def bake(self, object_name, resolution, samples, seed, max_bounces, guiding=False):
        """Cycles' DIFFUSE / INDIRECT bake of ``object_name``: (R, R, 4) float32, row 0 at the
        bottom, uncovered pixels = :data:`SENTINEL` (margin 0). Adaptive sampling and indirect
        clamping are off (unbiased, like the engine); total and diffuse bounces = ``max_bounces``.
        ``guiding``: Cycles' path guiding (Open PGL, ``scene.cycles.use_guiding``, surface
        guiding; the bake honours it on the CPU), restored afterwards."""
        obj = self.bpy.data.objects[object_name]
        cycles = self.bpy.context.scene.cycles
        saved = cycles.use_guiding
        cycles.use_guiding = bool(guiding)
        try:
            return self.demo.bake_cycles(self.bpy.context, obj, 'DIFFUSE', ('INDIRECT',), int(resolution),
                                         samples=int(samples), margin=0, margin_type='EXTEND',
                                         fill=SENTINEL, max_bounces=int(max_bounces), seed=int(seed),
                                         clamp_indirect=0.0)
        finally:
            cycles.use_guiding = saved

    def close(self):
        try:
            self._ext.unregister_checkout(self.module, self._repo)
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)
