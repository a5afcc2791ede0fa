"""Plain settings for every step, mirrored one to one by ``scene.lmdp`` in Blender.

Operators copy ``scene.lmdp`` into a :class:`Settings` (``Settings.from_mapping``) and pass it to
the engine; scripts and tests build one directly.
"""
from dataclasses import asdict, dataclass, field, fields, replace

COST_MODES = ("THESIS", "PHYSICAL")
SOLVERS = ("POWER", "DIRECT", "ITERATIVE")
BAKE_MODES = ("AUTO", "UNGUIDED", "GUIDED", "FINAL_GATHER", "RESIDUAL")
#: Where the bake's path length comes from (``scene.lmdp.light_paths``): the scene's Cycles
#: Light Paths, or ``Settings.max_bounces``.
LIGHT_PATHS = ("SCENE", "CUSTOM")
#: What a lightmap holds (``Settings.bake_content``): Cycles' DIFFUSE pass with pass_filter
#: {'INDIRECT'} or {'DIRECT', 'INDIRECT'} (``bake/content.py``).
BAKE_CONTENTS = ("INDIRECT", "DIRECT_INDIRECT")
#: The lightmap file of each object (``Settings.output_format``): OpenEXR full / half float,
#: Radiance HDR (``operators/adapters/lightmaps.py``).
OUTPUT_FORMATS = ("EXR_FLOAT", "EXR_HALF", "HDR")
#: An optional 8-bit copy next to it (``Settings.output_8bit``): none, PNG through the scene's
#: view transform, or RGBM PNG (``bake/encoding.py``).
OUTPUT_8BIT = ("NONE", "PNG", "RGBM")
#: How each object's lightmap size is chosen: ``bake_resolution`` for all, or from ``texel_density``.
RESOLUTION_MODES = ("FIXED", "DENSITY")


@dataclass
class Settings:
    # State space (thesis 3.1.1)
    point_count: int = 2048           #: surface points over the selected meshes
    strata_u: int = 4                 #: hemisphere strata along u of the Shirley–Chiu square
    strata_v: int = 4                 #: hemisphere strata along v
    # Passive dynamics (thesis 3.1.2)
    rays_per_stratum: int = 4         #: jittered rays cast through each stratum of each point
    light_samples: int = 32           #: shadow rays per point to the emitters (next-event estimation)
    epsilon: float = 5e-5             #: self-loop probability of eq. 3.1 (THESIS mode)
    # State costs (thesis 3.1.3)
    cost_mode: str = "PHYSICAL"       #: 'THESIS' (g = 1, Q = exp(-λ g)) or 'PHYSICAL' (Q = albedo)
    lambda_scale: float = 1.0         #: λ = (sum of light power per unit area) * lambda_scale
    # Solver (thesis 2.2.2 / 3.1.4)
    solver: str = "ITERATIVE"         #: 'POWER', 'DIRECT' or 'ITERATIVE'
    tolerance: float = 1e-8           #: relative change / residual at which the solver stops
    max_iterations: int = 10000       #: iteration cap of POWER and ITERATIVE
    # Bake (guided path tracing)
    bake_mode: str = "AUTO"           #: 'AUTO', 'UNGUIDED', 'GUIDED', 'FINAL_GATHER' or 'RESIDUAL' (docs/design.md)
    light_share: float = 0.5          #: UNGUIDED / GUIDED: share s of paths with a light vertex (light connections, bake/tracer)
    splitting: bool = True            #: GUIDED: Russian roulette and splitting by the solution (bake/splitting)
    path_reuse: int = 4               #: UNGUIDED / GUIDED: tiles of about N x N texels share their first bounces (1: off; bake/reuse)
    world_portals: bool = True        #: HDRI worlds: light samples where a probe saw the world (bake/portals)
    bake_resolution: int = 128        #: lightmap width = height in pixels
    bake_samples: int = 64            #: paths per texel
    bake_margin: int = 16             #: texels of dilation around UV islands (like Cycles)
    guide_fraction: float = 0.75      #: probability of sampling u* (vs cosine) in GUIDED mode
    max_bounces: int = 8              #: path length N of the tracer (Russian roulette after 3);
                                      #: the Blender layer puts LightPaths.path_length here
    clamp_direct: float = 0.0         #: Cycles' sample clamp of light reaching the texel directly
                                      #: (0: off; bake/clamp.py); SCENE: the scene's, by LightPaths
    clamp_indirect: float = 0.0       #: ... of light after a bounce (0: off); SCENE: the scene's
    # Lightmap content and output
    bake_content: str = "INDIRECT"    #: 'INDIRECT' or 'DIRECT_INDIRECT' (BAKE_CONTENTS)
    multiply_color: bool = False      #: times the texel's diffuse colour (Cycles' COLOR filter)
    denoise: bool = False             #: OIDN per UV island (Blender layer), the raw image kept
    output_format: str = "EXR_FLOAT"  #: lightmap files: 'EXR_FLOAT', 'EXR_HALF' or 'HDR'
    output_8bit: str = "NONE"         #: extra 8-bit file: 'NONE', 'PNG' or 'RGBM'
    # Lightmap layout (UV map, size per object, atlas)
    lightmap_uv_map: str = ""         #: UV map the lightmaps are laid out on ('' = "LMDP Lightmap"
                                      #: where a mesh has it, else its active render UV map)
    auto_lightmap_uvs: bool = True    #: create "LMDP Lightmap" where the chosen map is missing,
                                      #: overlaps, leaves [0, 1] or covers almost no texel
    resolution_mode: str = "FIXED"    #: 'FIXED' (bake_resolution) or 'DENSITY' (texel_density)
    texel_density: float = 32.0       #: DENSITY: texels per metre of surface
    min_resolution: int = 16          #: DENSITY: smallest lightmap side (pixels)
    max_resolution: int = 1024        #: DENSITY: largest lightmap side (pixels)
    power_of_two: bool = True         #: DENSITY: round each side up to a power of two
    atlas: bool = False               #: bake the objects into one shared lightmap image
    # Glossy surfaces: bounces counted apart, as Cycles does (-1: no separate limit, N). Not user
    # settings (no scene.lmdp property): LightPaths.apply sets them from the scene's Cycles Light Paths.
    glossy_bounces: int = field(default=-1, metadata={"light_paths": True})  #: Cycles' Glossy bounces
    total_bounces: int = field(default=-1, metadata={"light_paths": True})   #: Cycles' Max Bounces (any kind)
    #: Cycles' Min Light Bounces: with a clamp, Cycles' Russian roulette starts after it (bake/clamp.py)
    min_light_bounces: int = field(default=0, metadata={"light_paths": True})
    # Set by AUTO for the bake it chooses, not by the user (no scene.lmdp property).
    #: GUIDED: rays of the fine guide's table per path of the bake (0: ``FINE_RAYS_PER_PATH``;
    #: AUTO: ``SURE_TABLE_RAYS`` where unguided paths were very noisy; bake/fine_guide.py)
    guide_table_rays: float = field(default=0.0, metadata={"auto": True})
    # General
    seed: int = 0                     #: random seed; every step is deterministic for a seed
    output_dir: str = ""              #: where bakes / stats / exports are written ('' = nowhere)
    memory_budget_gb: float = 8.0     #: refuse builds and bakes whose memory estimate exceeds this (GiB)

    @property
    def strata_count(self):
        return int(self.strata_u) * int(self.strata_v)

    @classmethod
    def from_mapping(cls, mapping):
        """Build from any object or dict that has (a subset of) the field names."""
        values = {}
        for f in fields(cls):
            if isinstance(mapping, dict):
                if f.name in mapping:
                    values[f.name] = mapping[f.name]
            elif hasattr(mapping, f.name):
                values[f.name] = getattr(mapping, f.name)
        return cls(**values)

    def as_dict(self):
        return asdict(self)


@dataclass(frozen=True)
class LightPaths:
    """The path length a bake uses and where it comes from (``bake_stats.json`` "light_paths").

    ``SCENE``: the scene's Cycles Light Paths, as Cycles' own bake follows them. Cycles stops a
    path after the vertex whose bounce count reaches ``max_bounces`` or whose diffuse bounce count
    reaches ``diffuse_bounces`` (``path_state_next``, both limits + 1 in the kernel); the engine's
    path length is N = min(max_bounces, diffuse_bounces) (measured against Cycles' bakes:
    docs/design.md); on glossy surfaces (``bsdf``) a path counts its glossy bounces apart as
    Cycles does: at most ``glossy_bounces`` glossy, N diffuse and ``max_bounces`` in all
    (``apply``). Transparent surfaces absorb, so ``transparent_max_bounces`` is recorded only.
    ``clamp_direct`` / ``clamp_indirect`` are Cycles' ``sample_clamp_direct`` /
    ``sample_clamp_indirect`` (0: off), applied per light contribution as Cycles does
    (``bake/clamp.py``): biased by design, like Cycles.
    ``CUSTOM``: N = ``Settings.max_bounces`` and the clamps of ``Settings.clamp_direct`` /
    ``clamp_indirect`` (the add-on's own settings, 0 by default).
    """

    source: str                              #: 'SCENE' or 'CUSTOM'
    path_length: int                         #: N, the tracer's max_bounces
    max_bounces: int = None                  #: SCENE: Cycles' Max Bounces (Total)
    diffuse_bounces: int = None              #: SCENE: Cycles' Diffuse bounces
    glossy_bounces: int = None               #: SCENE: Cycles' Glossy bounces (recorded)
    transparent_max_bounces: int = None      #: SCENE: Cycles' Transparent bounces (recorded)
    clamp_indirect: float = 0.0              #: Cycles' Clamping > Indirect Light (0: off)
    clamp_direct: float = 0.0                #: Cycles' Clamping > Direct Light (0: off)
    min_light_bounces: int = 0               #: SCENE: Cycles' Min Light Bounces (the clamp's roulette)

    @classmethod
    def from_cycles(cls, max_bounces, diffuse_bounces, glossy_bounces=None, transparent_max_bounces=None,
                    clamp_indirect=0.0, clamp_direct=0.0, min_light_bounces=0):
        """The light paths of a scene whose Cycles settings have these values."""
        n = max(0, min(int(max_bounces), int(diffuse_bounces)))
        opt = (lambda v: None if v is None else int(v))
        return cls("SCENE", n, int(max_bounces), int(diffuse_bounces), opt(glossy_bounces),
                   opt(transparent_max_bounces), _limit(clamp_indirect), _limit(clamp_direct),
                   max(int(min_light_bounces), 0))

    @classmethod
    def custom(cls, max_bounces, clamp_direct=0.0, clamp_indirect=0.0):
        return cls("CUSTOM", int(max_bounces), clamp_indirect=_limit(clamp_indirect),
                   clamp_direct=_limit(clamp_direct))

    @property
    def clamped(self):
        """Some contributions are clamped (either limit is on)."""
        return self.clamp_direct > 0 or self.clamp_indirect > 0

    def apply(self, settings):
        """``settings`` with ``max_bounces`` = this path length and the two clamps and, for
        SCENE, Cycles' Glossy and Max bounces as ``glossy_bounces`` / ``total_bounces`` (paths
        through glossy surfaces count their glossy bounces apart; CUSTOM: -1, no separate limits)."""
        clamps = dict(clamp_direct=self.clamp_direct, clamp_indirect=self.clamp_indirect,
                      min_light_bounces=self.min_light_bounces)
        if self.source != "SCENE":
            return replace(settings, max_bounces=self.path_length, glossy_bounces=-1, total_bounces=-1, **clamps)
        glossy = -1 if self.glossy_bounces is None else max(int(self.glossy_bounces), 0)
        return replace(settings, max_bounces=self.path_length, glossy_bounces=glossy,
                       total_bounces=max(int(self.max_bounces), self.path_length), **clamps)

    def warnings(self):
        """Nothing to warn about the light paths themselves (the clamp's per-mode caveats are
        ``bake.checks``'); kept for callers that collect every stage's warnings."""
        return []

    def clamp_summary(self):
        """'no clamp', or which limits clamp: 'indirect clamped at 10 (biased, like Cycles)'."""
        if not self.clamped:
            return "no clamp"
        parts = [f"{kind} clamped at {value:g}" for kind, value in
                 (("direct", self.clamp_direct), ("indirect", self.clamp_indirect)) if value > 0]
        return " and ".join(parts) + " (biased, like Cycles)"

    def summary(self):
        """One line for the operator's report."""
        if self.source == "CUSTOM":
            return f"light paths: custom, {self.path_length} bounces, {self.clamp_summary()}"
        return (f"light paths: the scene's (Cycles max {self.max_bounces}, diffuse {self.diffuse_bounces}) "
                f"-> {self.path_length} bounces, {self.clamp_summary()}")

    def as_dict(self):
        d = asdict(self)
        d["clamp_applied"] = self.clamped
        return d


def _limit(value):
    """A clamp limit as Cycles reads it: a float, 0 (off) for anything not above 0."""
    value = float(value or 0.0)
    return value if value > 0 else 0.0
