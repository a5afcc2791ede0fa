"""Viewport overlay of the optimal policy: one gizmo that draws every u* arrow in one GPU batch.

``LMDP_GGT_policy`` is a persistent gizmo group of the 3D viewport; it is shown while the
scene's session holds a ``policy`` result (Show Policy, Probe) and ``scene.lmdp.show_policy_arrows``
is on. Its single gizmo draws the segments of :meth:`lmdp_addon.display.arrows.PolicyView.lines`
(arrows coloured by probability, crosses at the probe's next states) as one ``LINES`` batch,
so thousands of arrows stay interactive. The batch is rebuilt only when the policy result changes.

Headless Blender has no GPU drawing (``gpu`` raises in background mode): the shader and batch are
created lazily inside ``draw``, which never runs there. The gizmo cannot be selected or dragged.
"""
import bpy

from ..session import peek

LINE_WIDTH = 2.0


def policy_view(context):
    """The scene's :class:`~lmdp_addon.display.arrows.PolicyView` if the overlay should draw it."""
    scene = getattr(context, "scene", None)
    props = getattr(scene, "lmdp", None)
    if props is None or not props.show_policy_arrows:
        return None
    session = peek(scene)
    return session.get("policy") if session is not None else None


class LMDP_GT_policy_arrows(bpy.types.Gizmo):
    """Draws the policy arrows (not selectable)."""

    bl_idname = "LMDP_GT_policy_arrows"
    __slots__ = ("lmdp_batch", "lmdp_shader", "lmdp_view")

    def setup(self):
        self.lmdp_batch = None
        self.lmdp_shader = None
        self.lmdp_view = None  # the PolicyView the batch was built from (a reference, not an id)

    def _batch(self, view):
        import gpu
        from gpu_extras.batch import batch_for_shader
        if self.lmdp_shader is None:
            self.lmdp_shader = gpu.shader.from_builtin('POLYLINE_SMOOTH_COLOR')
        if self.lmdp_view is not view:
            vertices, colors = view.lines()
            self.lmdp_batch = batch_for_shader(self.lmdp_shader, 'LINES', {"pos": vertices, "color": colors}) \
                if len(vertices) else None
            self.lmdp_view = view
        return self.lmdp_batch

    def draw(self, context):
        view = policy_view(context)
        if view is None:
            return
        batch = self._batch(view)
        if batch is None:
            return
        import gpu
        region = context.region
        shader = self.lmdp_shader
        gpu.state.depth_test_set('LESS_EQUAL')
        gpu.state.blend_set('ALPHA')
        shader.bind()
        shader.uniform_float("viewportSize", (region.width, region.height))
        shader.uniform_float("lineWidth", LINE_WIDTH)
        batch.draw(shader)
        gpu.state.depth_test_set('NONE')
        gpu.state.blend_set('NONE')

    def test_select(self, context, location):
        return -1  # never selectable


class LMDP_GGT_policy(bpy.types.GizmoGroup):
    bl_idname = "LMDP_GGT_policy"
    bl_label = "LMDP Policy Arrows"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'WINDOW'
    bl_options = {'3D', 'PERSISTENT', 'SHOW_MODAL_ALL'}

    @classmethod
    def poll(cls, context):
        return policy_view(context) is not None

    def setup(self, context):
        gizmo = self.gizmos.new(LMDP_GT_policy_arrows.bl_idname)
        gizmo.hide_select = True
        gizmo.use_draw_modal = True
        self.arrows = gizmo


classes = (LMDP_GT_policy_arrows, LMDP_GGT_policy)
register, unregister = bpy.utils.register_classes_factory(classes)
