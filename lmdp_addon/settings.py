"""Plain settings for every step, mirrored one to one by ``scene.lmdp`` in Blender.

Operators copy ``scene.lmdp`` into a :class:`Settings` (``Settings.from_mapping``) and pass it to
the engine; scripts and tests build one directly.
"""
from dataclasses import asdict, dataclass, fields

COST_MODES = ("THESIS", "PHYSICAL")
SOLVERS = ("POWER", "DIRECT", "ITERATIVE")
BAKE_MODES = ("UNGUIDED", "GUIDED", "FINAL_GATHER")


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
    bake_mode: str = "GUIDED"         #: 'UNGUIDED', 'GUIDED' or 'FINAL_GATHER'
    bake_resolution: int = 128        #: lightmap width = height in pixels
    bake_samples: int = 64            #: paths per texel
    bake_margin: int = 16             #: texels of dilation around UV islands (like Cycles)
    guide_fraction: float = 0.5       #: probability of sampling u* (vs cosine) in GUIDED mode
    max_bounces: int = 8              #: path length cap of the tracer (Russian roulette after 3)
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
