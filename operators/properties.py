"""Scene settings: ``scene.lmdp``, one property per field of :class:`lmdp_addon.settings.Settings`.

Property names are public API (scripts and the README use them): add, never rename. Operators
read them with :func:`settings_from_scene`, which returns the engine's plain ``Settings``.
"""
import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..lmdp_addon.settings import (BAKE_MODES, COST_MODES, LIGHT_PATHS, RESOLUTION_MODES, SOLVERS, LightPaths,
                                    Settings)

_DEFAULTS = Settings()

#: Blender 4.5+ accepts (and warns without) this flag on paths that may start with '//'.
BLEND_RELATIVE_PATH = {'PATH_SUPPORTS_BLEND_RELATIVE'} if bpy.app.version >= (4, 5, 0) else set()

COST_MODE_ITEMS = (
    ("THESIS", "Thesis",
     "The thesis's LMDP (section 3.1): rows of P normalised to probabilities with an epsilon "
     "self-loop, state cost g = 1, Q = exp(-lambda g), emitters are goal states with z = 1"),
    ("PHYSICAL", "Physical",
     "Light transport: P = cosine-weighted form factors, Q = albedo, emitters fixed at their "
     "radiance, so z is the outgoing radiance (W/sr/m^2) and u* the zero-variance guide"),
)
SOLVER_ITEMS = (
    ("POWER", "Power Method",
     "The thesis's z-iteration z <- Q P z with the emitters fixed (thesis eq. 2.22, section 3.1.4)"),
    ("DIRECT", "Direct",
     "Sparse LU factorisation of (I - Q P) z = Q P z_terminal: exact, memory grows quickly"),
    ("ITERATIVE", "Iterative",
     "Krylov solver of (I - Q P) z = Q P z_terminal, falling back to the power method"),
)
BAKE_MODE_ITEMS = (
    ("AUTO", "Auto",
     "Unguided path tracing with light connections where its first samples are quiet; where they "
     "are noisy (light through an opening), the LMDP is solved (or the session's solution reused) and "
     "the rest is traced Guided when that is more efficient. Unbiased either way"),
    ("UNGUIDED", "Unguided",
     "Path tracing with cosine-weighted directions: the baseline estimator"),
    ("GUIDED", "Guided",
     "Path tracing with directions drawn from a mixture of the optimal policy u* and cosine "
     "sampling: unbiased, lower variance where light arrives from few directions"),
    ("FINAL_GATHER", "Final Gather",
     "One guided bounce, then the PHYSICAL-mode solution's indirect light at the hit plus the "
     "direct light sampled there: fast, biased by the discretisation"),
    ("RESIDUAL", "Residual",
     "Unbiased: the PHYSICAL-mode solution's first-bounce gather as a control variate, its mean "
     "from cheap one-bounce samples and the paths tracing only the residual"),
)
LIGHT_PATHS_ITEMS = (
    ("SCENE", "Scene",
     "Follow the scene's Cycles Light Paths as Cycles' own bake does: path length = the smaller of "
     "Max Bounces (Total) and Diffuse (bounces), and Cycles' Clamping (Direct / Indirect Light)"),
    ("CUSTOM", "Custom",
     "Use Max Bounces and the clamps below, whatever the scene's Cycles Light Paths"),
)
BAKE_CONTENT_ITEMS = (
    ("INDIRECT", "Indirect",
     "Light that bounced at least once before reaching the surface (Cycles' Diffuse bake, Indirect only)"),
    ("DIRECT_INDIRECT", "Direct + Indirect",
     "All the light reaching the surface: straight from lights and the world, and bounced "
     "(Cycles' Diffuse bake, Direct and Indirect)"),
)
OUTPUT_FORMAT_ITEMS = (
    ("EXR_FLOAT", "OpenEXR (float)", "32-bit float OpenEXR (.exr), lossless"),
    ("EXR_HALF", "OpenEXR (half)", "16-bit half float OpenEXR (.exr): half the size, 3 significant digits"),
    ("HDR", "Radiance HDR", "Radiance RGBE (.hdr): 8-bit mantissas with a shared exponent, about 1 % precision"),
)
OUTPUT_8BIT_ITEMS = (
    ("NONE", "None", "No 8-bit copy"),
    ("PNG", "PNG (view transform)",
     "8-bit sRGB PNG '<lightmap>_srgb.png' through the scene's view transform, look and exposure "
     "(Color Management): what a render shows, clipped at white"),
    ("RGBM", "RGBM PNG",
     "8-bit RGBM PNG '<lightmap>_rgbm.png', linear: value = rgb x a x 7 (values up to 7 are kept; "
     "three.js RGBMLoader's default range)"),
)
RESOLUTION_MODE_ITEMS = (
    ("FIXED", "Fixed", "Every lightmap is Resolution x Resolution pixels"),
    ("DENSITY", "Texel Density",
     "Each object's lightmap side from its surface area: Texel Density x sqrt(area / UV area), "
     "clamped to Min / Max Resolution (optionally a power of two)"),
)
DISPLAY_QUANTITY_ITEMS = (
    ("Z", "Desirability z",
     "Desirability z (in PHYSICAL mode the outgoing radiance, W/sr/m^2), on a log colour scale"),
    ("COST_TO_GO", "Cost-to-go J",
     "Optimal cost-to-go J = -(log z) / lambda: expected cost of reaching a light from the state"),
    ("RESIDUAL", "Residual",
     "Per-state residual |z - Q P z| of the solve: where the solution is least converged"),
)
DISPLAY_COLORMAP_ITEMS = (
    ("VIRIDIS", "Viridis", "Dark blue to yellow, perceptually uniform (matplotlib's viridis)"),
    ("INFERNO", "Inferno", "Black to light yellow, perceptually uniform (matplotlib's inferno)"),
)
POLICY_SUBSET_ITEMS = (
    ("ACTIVE_OBJECT", "Active Object", "Arrows for the states on the active object"),
    ("MOST_INFORMATIVE", "Most Informative",
     "Arrows for the states whose optimal policy differs most from the passive dynamics"),
)

for _items, _identifiers in ((COST_MODE_ITEMS, COST_MODES), (SOLVER_ITEMS, SOLVERS),
                             (BAKE_MODE_ITEMS, BAKE_MODES), (LIGHT_PATHS_ITEMS, LIGHT_PATHS),
                             (RESOLUTION_MODE_ITEMS, RESOLUTION_MODES)):
    assert tuple(item[0] for item in _items) == tuple(_identifiers), "enum items out of sync with the engine"


class LMDPSceneSettings(bpy.types.PropertyGroup):
    """Settings of every LMDP stage for this scene (``scene.lmdp``)."""

    # -- State space (thesis 3.1.1) ---------------------------------------------------------------
    point_count: IntProperty(
        name="Points",
        description="Number of surface points sampled over the selected meshes, proportional to "
                    "world-space area (count). Each point carries one state per hemisphere stratum",
        default=_DEFAULTS.point_count, min=1, max=10_000_000, soft_min=16, soft_max=200_000,
    )
    strata_u: IntProperty(
        name="Strata U",
        description="Hemisphere strata along u of the Shirley-Chiu square (count); all strata "
                    "have the same solid angle, 2 pi / (U x V) sr",
        default=_DEFAULTS.strata_u, min=1, max=64, soft_max=16,
    )
    strata_v: IntProperty(
        name="Strata V",
        description="Hemisphere strata along v of the Shirley-Chiu square (count); all strata "
                    "have the same solid angle, 2 pi / (U x V) sr",
        default=_DEFAULTS.strata_v, min=1, max=64, soft_max=16,
    )
    # -- Passive dynamics (thesis 3.1.2) ------------------------------------------------------------
    rays_per_stratum: IntProperty(
        name="Rays per Stratum",
        description="Jittered rays cast through each stratum of each point to estimate the "
                    "passive dynamics P (rays). More rays: less noise in P, longer build",
        default=_DEFAULTS.rays_per_stratum, min=1, max=4096, soft_max=64,
    )
    light_samples: IntProperty(
        name="Light Samples",
        description="Shadow rays per point towards the emitters (next-event estimation of the "
                    "transitions into emitter states, rays). 0: only the stratum rays find the "
                    "lights (noisy for small lights)",
        default=_DEFAULTS.light_samples, min=0, max=65536, soft_max=1024,
    )
    epsilon: FloatProperty(
        name="Self-loop Epsilon",
        description="Self-loop probability added to every row of P in THESIS mode (thesis eq. "
                    "3.1, probability, unitless)",
        default=_DEFAULTS.epsilon, min=0.0, max=1.0, soft_max=0.01, precision=6, step=0.001,
    )
    # -- State costs (thesis 3.1.3) -----------------------------------------------------------------
    cost_mode: EnumProperty(
        name="Cost Mode",
        description="How the state costs Q and the terminal desirability are defined",
        items=COST_MODE_ITEMS, default=_DEFAULTS.cost_mode,
    )
    lambda_scale: FloatProperty(
        name="Lambda Scale",
        description="THESIS mode: lambda = (sum over lights of their exitance, W/m^2) x this "
                    "factor (unitless). Small: slow convergence, u* close to P; large: sharp u*",
        default=_DEFAULTS.lambda_scale, min=1e-9, max=1e9, soft_min=1e-4, soft_max=100.0,
        precision=4,
    )
    # -- Solver (thesis 2.2.2, 3.1.4) ---------------------------------------------------------------
    solver: EnumProperty(
        name="Solver",
        description="Method that solves for the desirability z",
        items=SOLVER_ITEMS, default=_DEFAULTS.solver,
    )
    tolerance: FloatProperty(
        name="Tolerance",
        description="Relative change (power method) or relative residual (iterative) at which "
                    "the solver stops (unitless, e.g. 1e-8)",
        default=_DEFAULTS.tolerance, min=1e-15, max=0.1, soft_min=1e-12, soft_max=1e-2,
        precision=6, step=1e-4,
    )
    max_iterations: IntProperty(
        name="Max Iterations",
        description="Iteration cap of the POWER and ITERATIVE solvers (iterations)",
        default=_DEFAULTS.max_iterations, min=1, max=10_000_000, soft_max=100_000,
    )
    # -- Bake (guided path tracing) -----------------------------------------------------------------
    bake_mode: EnumProperty(
        name="Bake Mode",
        description="Estimator used to bake indirect light into image textures",
        items=BAKE_MODE_ITEMS, default=_DEFAULTS.bake_mode,
    )
    bake_resolution: IntProperty(
        name="Resolution",
        description="Width and height of each baked lightmap (pixels)",
        default=_DEFAULTS.bake_resolution, min=1, max=16384, soft_min=16, soft_max=4096,
        subtype='PIXEL',
    )
    bake_samples: IntProperty(
        name="Samples",
        description="Paths traced per texel (paths)",
        default=_DEFAULTS.bake_samples, min=1, max=1_000_000, soft_max=4096,
    )
    bake_margin: IntProperty(
        name="Margin",
        description="Dilation around UV islands, like Cycles' bake margin (pixels)",
        default=_DEFAULTS.bake_margin, min=0, max=512, soft_max=64, subtype='PIXEL',
    )
    guide_fraction: FloatProperty(
        name="Guide Fraction",
        description="GUIDED (also AUTO's guided part) and FINAL_GATHER: probability of drawing a direction from the optimal policy u* "
                    "instead of cosine sampling (probability, 0..1)",
        default=_DEFAULTS.guide_fraction, min=0.0, max=1.0, subtype='FACTOR',
    )
    light_share: FloatProperty(
        name="Light Connections",
        description="AUTO, UNGUIDED and GUIDED: share of paths that also trace a ray from a light and join its first "
                    "hit to every diffuse vertex of the path (unbiased; finds light reflected by surfaces "
                    "right beside a lamp). Off while a sample clamp is on, or with transparent materials "
                    "(share, 0..1; 0: off)",
        default=_DEFAULTS.light_share, min=0.0, max=1.0, subtype='FACTOR',
    )
    path_reuse: IntProperty(
        name="Path Reuse",
        description="AUTO, UNGUIDED and GUIDED: tiles of about N x N neighbouring texels share the light their "
                    "first bounces found, each texel weighting the others' first hits by the balance heuristic "
                    "(a shadow ray each; unbiased; far less noise per sample). Off while a sample clamp is on, "
                    "or with transparent materials (texels per side; 1: off)",
        default=_DEFAULTS.path_reuse, min=1, max=8,
    )
    splitting: BoolProperty(
        name="Splitting",
        description="GUIDED (also AUTO's guided part): Russian roulette and splitting by the solution: paths "
                    "that head where the solved LMDP sees much light (through an opening) are kept and split, "
                    "paths in dim places end sooner (unbiased)",
        default=_DEFAULTS.splitting,
    )
    world_portals: BoolProperty(
        name="World Portals",
        description="HDRI worlds: a probe of a few thousand paths learns which parts of the environment map the "
                    "baked surfaces see (through windows and openings) and the bake sends the world's light "
                    "samples there, per object (unbiased; AUTO's first measurement is the probe)",
        default=_DEFAULTS.world_portals,
    )
    light_paths: EnumProperty(
        name="Light Paths",
        description="Where the bake's path length comes from: the scene's Cycles Light Paths "
                    "(Render Properties > Light Paths), or Max Bounces",
        items=LIGHT_PATHS_ITEMS, default='SCENE',
    )
    max_bounces: IntProperty(
        name="Max Bounces",
        description="Light Paths Custom: path length of the tracer, as Cycles' Max Bounces with Diffuse "
                    "bounces at least as many; Russian roulette starts after 3 (bounces)",
        default=_DEFAULTS.max_bounces, min=1, max=1024, soft_max=64,
    )
    clamp_direct: FloatProperty(
        name="Clamp Direct",
        description="Light Paths Custom: as Cycles' Clamping > Direct Light, the largest sum of the three "
                    "channels of one sample of light reaching the surface straight from a light, divided "
                    "by 3 (radiance); brighter samples are scaled down to it (biased). 0 turns it off",
        default=_DEFAULTS.clamp_direct, min=0.0, max=1e6, soft_max=100.0,
    )
    clamp_indirect: FloatProperty(
        name="Clamp Indirect",
        description="Light Paths Custom: as Cycles' Clamping > Indirect Light, the largest sum of the three "
                    "channels of one sample of light that bounced first, divided by 3 (radiance); brighter "
                    "samples are scaled down to it, which removes fireflies (biased). 0 turns it off",
        default=_DEFAULTS.clamp_indirect, min=0.0, max=1e6, soft_max=100.0,
    )
    # -- Lightmap content and output (bake_content ... output_8bit) --------------------------------
    bake_content: EnumProperty(
        name="Bake Content",
        description="What the lightmap holds, as Cycles' Diffuse bake with the same Contributions",
        items=BAKE_CONTENT_ITEMS, default=_DEFAULTS.bake_content,
    )
    multiply_color: BoolProperty(
        name="Times Diffuse Colour",
        description="Multiply the light by the surface's diffuse colour (Cycles' Diffuse bake with "
                    "Color on): a combined diffuse lightmap that replaces the surface's colour",
        default=_DEFAULTS.multiply_color,
    )
    denoise: BoolProperty(
        name="Denoise",
        description="Denoise each lightmap with Open Image Denoise (the compositor's Denoise node, with "
                    "the texels' diffuse colour and normal as guides), each UV island on its own so no "
                    "light crosses between islands; the raw lightmap is kept as '<image>_raw'",
        default=_DEFAULTS.denoise,
    )
    output_format: EnumProperty(
        name="Output Format",
        description="File format of the lightmaps written to the Output Folder",
        items=OUTPUT_FORMAT_ITEMS, default=_DEFAULTS.output_format,
    )
    output_8bit: EnumProperty(
        name="8-bit Copy",
        description="Also write an 8-bit PNG of each lightmap to the Output Folder, for engines "
                    "that cannot read float images",
        items=OUTPUT_8BIT_ITEMS, default=_DEFAULTS.output_8bit,
    )
    # -- Lightmap layout (UV map, size per object, atlas) --------------------------------------------
    lightmap_uv_map: StringProperty(
        name="Lightmap UV Map",
        description="UV map the lightmaps are laid out on (and read through by the hook-up); empty: "
                    "'LMDP Lightmap' where a mesh has it, else its active render UV map",
        default=_DEFAULTS.lightmap_uv_map,
    )
    auto_lightmap_uvs: BoolProperty(
        name="Auto Lightmap UVs",
        description="Before baking, create the UV map 'LMDP Lightmap' (Smart UV Project + Pack Islands) on "
                    "meshes whose lightmap UV map is missing, overlaps, leaves [0, 1] or has islands "
                    "smaller than a texel; the other UV maps and the render UV map are not changed",
        default=_DEFAULTS.auto_lightmap_uvs,
    )
    resolution_mode: EnumProperty(
        name="Size",
        description="How each object's lightmap size is chosen",
        items=RESOLUTION_MODE_ITEMS, default=_DEFAULTS.resolution_mode,
    )
    texel_density: FloatProperty(
        name="Texel Density",
        description="Texel Density size: lightmap texels per metre of surface (texels/m)",
        default=_DEFAULTS.texel_density, min=1e-3, max=1e5, soft_min=1.0, soft_max=1024.0,
    )
    min_resolution: IntProperty(
        name="Min Resolution",
        description="Texel Density size: smallest lightmap side (pixels)",
        default=_DEFAULTS.min_resolution, min=1, max=16384, subtype='PIXEL',
    )
    max_resolution: IntProperty(
        name="Max Resolution",
        description="Texel Density size: largest lightmap side (pixels)",
        default=_DEFAULTS.max_resolution, min=1, max=16384, subtype='PIXEL',
    )
    power_of_two: BoolProperty(
        name="Power of Two",
        description="Texel Density size: round each lightmap side up to a power of two (pixels)",
        default=_DEFAULTS.power_of_two,
    )
    atlas: BoolProperty(
        name="Atlas",
        description="Bake the selected objects into one shared image 'LMDP Atlas_lmdp_indirect', each in its "
                    "own region of its 'LMDP Lightmap' UV map (packed together); shared materials are hooked "
                    "up through it",
        default=_DEFAULTS.atlas,
    )
    # -- General ------------------------------------------------------------------------------------
    seed: IntProperty(
        name="Seed",
        description="Random seed: every stage is deterministic for a given seed",
        default=_DEFAULTS.seed, min=0,
    )
    output_dir: StringProperty(
        name="Output Folder",
        description="Folder where baked lightmaps (OpenEXR), statistics and exports are written; "
                    "empty: nothing is written to disk",
        default=_DEFAULTS.output_dir, subtype='DIR_PATH', options=BLEND_RELATIVE_PATH,
    )
    memory_budget_gb: FloatProperty(
        name="Memory Budget",
        description="Refuse to build or bake problems whose estimated memory exceeds this (GiB)",
        default=_DEFAULTS.memory_budget_gb, min=0.01, max=4096.0, soft_max=64.0, precision=2,
    )

    # -- Display (visualisation of z / J / u* in the viewport) --------------------------------------
    display_quantity: EnumProperty(
        name="Show",
        description="Quantity written as vertex colours by Show Desirability",
        items=DISPLAY_QUANTITY_ITEMS, default='Z',
    )
    policy_subset: EnumProperty(
        name="Policy States",
        description="Which states get optimal-policy arrows",
        items=POLICY_SUBSET_ITEMS, default='ACTIVE_OBJECT',
    )
    policy_max_points: IntProperty(
        name="Max Points",
        description="Largest number of surface points that get policy arrows (points)",
        default=200, min=1, max=100_000, soft_max=5000,
    )
    policy_arrow_scale: FloatProperty(
        name="Arrow Scale",
        description="Length of a policy arrow of probability 1 (metres)",
        default=0.1, min=0.0, max=1000.0, soft_min=0.001, soft_max=10.0, subtype='DISTANCE',
        unit='LENGTH',
    )
    display_colormap: EnumProperty(
        name="Colour Map",
        description="Perceptual colour map of Show Desirability (log scale for z and the "
                    "residual, linear for J)",
        items=DISPLAY_COLORMAP_ITEMS, default='VIRIDIS',
    )
    display_subdivide: BoolProperty(
        name="Subdivide Coarse Meshes",
        description="Show the field at the resolution of the states on meshes whose faces are "
                    "larger than the state spacing (a Cornell-box wall is one quad): adds an "
                    "'LMDP Display' geometry-nodes modifier that subdivides the evaluated mesh "
                    "and carries the finer colours. The mesh data itself is not changed",
        default=False,
    )
    display_max_level: IntProperty(
        name="Max Level",
        description="Largest subdivision level of the LMDP Display modifier (each level splits "
                    "every face into 4, levels)",
        default=6, min=1, max=8,
    )
    show_policy_arrows: BoolProperty(
        name="Draw Arrows",
        description="Draw the optimal-policy arrows of Show Policy and Probe in the 3D viewport "
                    "(gizmo overlay; hidden when the viewport's gizmos are off)",
        default=True,
    )

    # -- Run All ------------------------------------------------------------------------------------
    run_all_show: BoolProperty(
        name="Show",
        description="Run All also shows the desirability on the selected meshes (Show Desirability)",
        default=True,
    )
    run_all_bake: BoolProperty(
        name="Bake",
        description="Run All also bakes the indirect light of the selected meshes (Bake; every "
                    "selected mesh needs a UV map)",
        default=True,
    )

    # -- Internal -----------------------------------------------------------------------------------
    session_id: StringProperty(
        name="Session ID",
        description="Internal: identifies this scene's in-memory LMDP results (not user data)",
        default="", options={'HIDDEN'},
    )

    @classmethod
    def register(cls):
        bpy.types.Scene.lmdp = PointerProperty(
            type=cls, name="LMDP Light Transport", description="LMDP Light Transport settings")

    @classmethod
    def unregister(cls):
        del bpy.types.Scene.lmdp


#: Settings fields stored as 32-bit floats by Blender: read back with 7 significant digits.
_FLOAT_FIELDS = frozenset(name for name, value in Settings().as_dict().items() if isinstance(value, float))


def settings_from_scene(scene):
    """The engine's :class:`Settings` for ``scene`` (a copy of ``scene.lmdp``).

    Blender stores float properties in single precision: they are rounded to 7 significant
    digits so that a tolerance typed as 1e-8 reaches the engine as 1e-8, not 9.99999994e-09.
    ``output_dir`` is made absolute (Blender's ``//`` prefix means "next to the .blend file");
    in a file that was never saved a ``//`` path is kept as it is, and the operators that write
    there refuse it (``adapters.lightmaps.resolve_output_folder``).
    """
    props = scene.lmdp
    values = {}
    for name in Settings().as_dict():
        if not hasattr(props, name):
            continue
        value = getattr(props, name)
        if name in _FLOAT_FIELDS:
            value = float(f"{value:.7g}")
        elif name == "output_dir" and value and not (value.startswith("//") and not bpy.data.filepath):
            value = bpy.path.abspath(value)  # '//bakes/' is relative to the .blend file
        values[name] = value
    return Settings.from_mapping(values)


def light_paths_from_scene(scene):
    """The :class:`~lmdp_addon.settings.LightPaths` of a bake of ``scene``: ``scene.lmdp.light_paths``
    'SCENE' reads the scene's Cycles Light Paths (``scene.cycles``: bounces and both clamps),
    'CUSTOM' ``scene.lmdp.max_bounces``, ``clamp_direct`` and ``clamp_indirect``."""
    props = scene.lmdp
    cycles = getattr(scene, "cycles", None)
    if props.light_paths == 'CUSTOM' or cycles is None:
        return LightPaths.custom(props.max_bounces, float(f"{props.clamp_direct:.7g}"),
                                 float(f"{props.clamp_indirect:.7g}"))
    return LightPaths.from_cycles(cycles.max_bounces, cycles.diffuse_bounces, cycles.glossy_bounces,
                                  cycles.transparent_max_bounces, float(f"{cycles.sample_clamp_indirect:.7g}"),
                                  float(f"{cycles.sample_clamp_direct:.7g}"), cycles.min_light_bounces)


def bake_settings_from_scene(scene):
    """``(Settings, LightPaths)`` of a bake of ``scene``: :func:`settings_from_scene` with
    ``max_bounces`` = the path length and the clamps of :func:`light_paths_from_scene`."""
    light_paths = light_paths_from_scene(scene)
    return light_paths.apply(settings_from_scene(scene)), light_paths


classes = (LMDPSceneSettings,)
register, unregister = bpy.utils.register_classes_factory(classes)
