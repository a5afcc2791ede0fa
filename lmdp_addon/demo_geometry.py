"""Built-in test scenes as named parts: the same geometry for the engine and for Blender.

Every scene is a list of :class:`Part` objects (one Blender object each): quads (polygons of four
corners) with per-corner UVs, a diffuse albedo or an emitted radiance. The engine gets them as
:class:`~lmdp_addon.scene_arrays.SceneArrays` through :func:`build_scene_arrays`; the Blender layer
(``operators/adapters/demo_scenes.py``) turns the same parts into mesh objects with Diffuse BSDF / Emission
materials, so an extraction of the Blender scene gives back the same triangles.

Units and conventions (those of ``SceneArrays``): world metres, Z up, linear RGB albedo, emitted
radiance in W / (sr m^2) per channel (an Emission shader of strength S and colour c has radiance
S·c), mesh emission two-sided (like Cycles). A quad ``(a, b, c, d)`` is split into the triangles
``(a, b, c)`` and ``(a, c, d)`` (Blender's split of a planar quad); its normal follows the
right-hand rule. Closed boxes have outward normals; the room's walls face into the room.

Scenes (``kind``):

* ``CORNELL_BOX``: the Cornell box at unit scale: a 1 m cube room open at the front (-Y), white
  floor, ceiling and back wall, red left wall, green right wall, a tall and a short box, and an
  emissive quad just below the ceiling facing down.
* ``NARROW_OPENING``: two rooms separated by a thick wall with a small hatch; the only emitter is in
  the right room (``RoomB``), so the left room (``RoomA``) is lit only through the opening. Every
  part is a closed box (the dividing wall is a closed slab with a hole), so no single-sided plane
  is ever seen from its back.
* ``PLANE_UNDER_SKY``: one diffuse plane under a uniform world: outgoing radiance = albedo x L.
* ``PARALLEL_SQUARES``: a receiving plane under a parallel square emitter; the irradiance at a
  point is π L F with F from :func:`point_to_parallel_square_form_factor`.
* ``HEAVY``: the Cornell box with finely subdivided, bumpy walls and boxes (> 200k triangles), for
  benchmarks.
* ``GLOSSY_BOX``: the Cornell box with a glossy checkered floor (Principled BSDF, roughness 0.2,
  default specular) and a metallic sphere (Principled, Metallic 1) in place of the short box
  (issue 18, item 3). The checker is a per-face colour (:func:`floor_checker`, the hook an image
  texture replaces once textures reach the engine).
"""
from dataclasses import dataclass, field

import numpy as np

from . import bsdf
from .errors import SceneError
from .demo_uv import UV_PADDING, grid_uv, quad_charts, quad_dims, shelf_pack
from .scene_arrays import SceneArrays

#: Scene kinds, in the order the UI lists them.
SCENE_KINDS = ("CORNELL_BOX", "NARROW_OPENING", "PLANE_UNDER_SKY", "PARALLEL_SQUARES", "HEAVY", "GLOSSY_BOX")

# Cornell box reflectances (linear RGB), close to the measured spectra of the original box.
WHITE = (0.73, 0.73, 0.73)
RED = (0.63, 0.065, 0.05)
GREEN = (0.14, 0.45, 0.091)
#: Radiance of the Cornell box light, W / (sr m^2) per channel (warm white, strength 40).
CORNELL_LIGHT_RADIANCE = (40.0, 34.0, 24.0)


@dataclass
class Part:
    """One object of a built-in scene.

    vertices      (V, 3) float64 world metres
    faces         (F, 4) int64 quads, corners counter-clockwise seen from the front
    face_uv       (F, 4, 2) float32 UV of each quad corner (non-overlapping charts in [0, 1]^2)
    albedo        (3,) diffuse reflectance (0 for emitters); with ``principled``: its Base Color
    emission      (3,) emitted radiance W / (sr m^2) (0 for reflectors)
    two_sided_emission  bool: mesh emission is two-sided in Cycles
    principled    None (a Diffuse BSDF) or the Principled BSDF inputs of the part's material:
                  ``roughness``, ``metallic``, ``ior``, ``ior_level`` (``bsdf.principled_lobes``)
    face_albedo   None or (F, 3) a colour per face (a checker) in place of ``albedo``
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    face_uv: np.ndarray
    albedo: np.ndarray = field(default_factory=lambda: np.zeros(3))
    emission: np.ndarray = field(default_factory=lambda: np.zeros(3))
    two_sided_emission: bool = True
    principled: dict = None
    face_albedo: np.ndarray = None

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 4)
        self.face_uv = np.asarray(self.face_uv, dtype=np.float32).reshape(-1, 4, 2)
        self.albedo = np.asarray(self.albedo, dtype=np.float64).reshape(3)
        self.emission = np.asarray(self.emission, dtype=np.float64).reshape(3)
        if self.face_albedo is not None:
            self.face_albedo = np.asarray(self.face_albedo, dtype=np.float64).reshape(len(self.faces), 3)

    @property
    def base_colours(self):
        """(C, 3) the part's distinct colours and (F,) the colour of each face."""
        if self.face_albedo is None:
            return self.albedo[None, :], np.zeros(len(self.faces), dtype=np.int64)
        colours, index = np.unique(self.face_albedo, axis=0, return_inverse=True)
        return colours, index.reshape(-1)

    @property
    def triangle_albedo(self):
        """(2F, 3) diffuse reflectance per triangle: the face colour x (1 - Metallic)."""
        colours, index = self.base_colours
        diffuse = colours * (1.0 - (self.principled or {}).get("metallic", 0.0))
        return np.repeat(diffuse[index], 2, axis=0)

    def lobes(self, colour):
        """The microfacet lobes of the part's material of Base Color ``colour`` (none for a
        Diffuse BSDF)."""
        if self.principled is None:
            return []
        p = self.principled
        return bsdf.principled_lobes(colour, p.get("metallic", 0.0), p.get("roughness", 0.5), p.get("ior", 1.5),
                                     p.get("ior_level", 0.5))

    @property
    def is_emitter(self):
        return bool(np.any(self.emission > 0))

    @property
    def triangles(self):
        """(2F, 3) int64: quad f gives triangles 2f = (a, b, c) and 2f + 1 = (a, c, d)."""
        f = self.faces
        return np.stack([f[:, [0, 1, 2]], f[:, [0, 2, 3]]], axis=1).reshape(-1, 3)

    @property
    def uv(self):
        """(2F, 3, 2) float32 per-triangle corner UVs, in the order of :attr:`triangles`."""
        u = self.face_uv
        return np.stack([u[:, [0, 1, 2]], u[:, [0, 2, 3]]], axis=1).reshape(-1, 3, 2)

    @property
    def n_triangles(self):
        return 2 * len(self.faces)


@dataclass
class CameraView:
    """Where the demo camera stands: ``location`` and ``look_at`` in metres, ``fov`` in radians."""

    location: tuple
    look_at: tuple
    fov: float


# -- analytic references -----------------------------------------------------------------------

def _form_factor_corner(x, y):
    """Form factor from a point to a parallel rectangle [0, x] x [0, y] at unit height.

    The rectangle has one corner straight above the point; x, y are its sides divided by the
    height (signed: a negative side gives a negative contribution, for superposition).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ax = np.sqrt(1.0 + x * x)
    ay = np.sqrt(1.0 + y * y)
    return (x / ax * np.arctan(y / ax) + y / ay * np.arctan(x / ay)) / (2.0 * np.pi)


def point_to_parallel_square_form_factor(side, height, offset=(0.0, 0.0), side_y=None):
    """Differential form factor F from a point to a parallel rectangle facing it.

    ``side`` (x) by ``side_y`` (y, default ``side``) metres, centred at ``height`` metres above the
    point's plane, its centre displaced by ``offset (..., 2)`` from the point along the plane. The
    irradiance from a Lambertian emitter of radiance L is E = π L F, so a diffuse receiver of
    albedo ρ has outgoing radiance ρ L F and Cycles' DIFFUSE DIRECT bake (E/π) gives L F.
    Vectorised over ``offset``.
    """
    side_y = side if side_y is None else side_y
    off = np.asarray(offset, dtype=np.float64)
    h = float(height)
    dx, dy = off[..., 0], off[..., 1]
    x1, x2 = (dx - side / 2.0) / h, (dx + side / 2.0) / h
    y1, y2 = (dy - side_y / 2.0) / h, (dy + side_y / 2.0) / h
    # Superposition of corner rectangles with signed sides.
    return (_form_factor_corner(x2, y2) - _form_factor_corner(x1, y2)
            - _form_factor_corner(x2, y1) + _form_factor_corner(x1, y1))


# -- geometry helpers -------------------------------------------------------------------------

def _rotation_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _grid(origin, edge_u, edge_v, nu, nv, bump=0.0, bump_waves=3.0):
    """An nu x nv grid of quads on the parallelogram origin + s edge_u + t edge_v.

    Returns vertices ((nu+1)(nv+1), 3) and faces (nu nv, 4), normals along edge_u x edge_v. With
    ``bump`` (metres) the vertices move along the normal by a smooth bump field that vanishes on
    the border, so neighbouring grids still meet.
    """
    origin, edge_u, edge_v = (np.asarray(a, dtype=np.float64) for a in (origin, edge_u, edge_v))
    s = np.linspace(0.0, 1.0, nu + 1)
    t = np.linspace(0.0, 1.0, nv + 1)
    ss, tt = np.meshgrid(s, t, indexing="xy")
    verts = origin + ss[..., None] * edge_u + tt[..., None] * edge_v
    if bump:
        normal = np.cross(edge_u, edge_v)
        normal /= np.linalg.norm(normal)
        envelope = np.sin(np.pi * ss) * np.sin(np.pi * tt)
        field_ = np.sin(2 * np.pi * bump_waves * ss) * np.cos(2 * np.pi * bump_waves * tt)
        verts = verts + (bump * envelope * field_)[..., None] * normal
    verts = verts.reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="xy")
    i, j = i.ravel(), j.ravel()
    row = nu + 1
    faces = np.stack([j * row + i, j * row + i + 1, (j + 1) * row + i + 1, (j + 1) * row + i], axis=1)
    return verts, faces


def _quad_part(name, corners, albedo=(0, 0, 0), emission=(0, 0, 0)):
    """A single-quad part; ``corners (4, 3)`` counter-clockwise seen from the front side."""
    return Part(name, np.asarray(corners, dtype=np.float64), [[0, 1, 2, 3]],
                quad_charts(np.asarray(corners), [[0, 1, 2, 3]]), albedo, emission)


def _box_faces():
    """Quads of the box with corners indexed by bits (x, y, z) = (i & 1, i >> 1 & 1, i >> 2 & 1).

    Corner order gives outward normals.
    """
    return np.array([
        [0, 2, 3, 1],  # bottom (-z)
        [4, 5, 7, 6],  # top (+z)
        [0, 1, 5, 4],  # front (-y)
        [3, 2, 6, 7],  # back (+y)
        [2, 0, 4, 6],  # left (-x)
        [1, 3, 7, 5],  # right (+x)
    ])


def _box_corners(center, size, angle=0.0):
    bits = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64)
    local = (bits - 0.5) * np.asarray(size, dtype=np.float64)
    return local @ _rotation_z(angle).T + np.asarray(center, dtype=np.float64)


def _box_part(name, center, size, albedo, angle=0.0):
    """A closed box (6 quads, outward normals, 8 shared vertices), rotated by ``angle`` about Z."""
    verts = _box_corners(center, size, angle)
    faces = _box_faces()
    return Part(name, verts, faces, quad_charts(verts, faces), albedo)


def _subdivided_box_part(name, center, size, albedo, angle, n, bump):
    """A closed box whose faces are n x n grids (bumpy), each grid in its own UV chart."""
    corners = _box_corners(center, size, angle)
    quads = _box_faces()
    dims = quad_dims(corners, quads)
    chart_pos, chart_size = shelf_pack(dims, UV_PADDING)
    verts, faces, uvs = [], [], []
    offset = 0
    for q, (chart_lo, chart_sz) in zip(quads, zip(chart_pos, chart_size)):
        a, b, _, d = corners[q]
        v, f = _grid(a, b - a, d - a, n, n, bump=bump)
        verts.append(v)
        faces.append(f + offset)
        uvs.append(grid_uv(n, n, chart_lo, chart_lo + chart_sz))
        offset += len(v)
    return Part(name, np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs), albedo)


def _holed_slab_part(name, x_range, y_range, z_range, hole_y, hole_z, albedo):
    """A closed slab (thickness along x) with a rectangular hole through it along x.

    Each big face is a 3 x 3 grid of quads around the hole (the middle cell left out), the rim is
    split to match, and 4 reveals line the hole, so every edge is shared by exactly two quads
    (a closed 2-manifold, no T-junctions); normals point out of the solid. Each quad gets its
    own UV chart.
    """
    x0, x1 = x_range
    ys = [y_range[0], hole_y[0], hole_y[1], y_range[1]]
    zs = [z_range[0], hole_z[0], hole_z[1], z_range[1]]
    quads = []
    for x, facing in ((x1, +1), (x0, -1)):
        for yi in range(3):
            for zi in range(3):
                if yi == 1 and zi == 1:
                    continue  # the hole
                a = (x, ys[yi], zs[zi])
                b = (x, ys[yi + 1], zs[zi])
                c = (x, ys[yi + 1], zs[zi + 1])
                d = (x, ys[yi], zs[zi + 1])
                # Counter-clockwise seen from +x is (a, b, c, d) with y right and z up.
                quads.append([a, b, c, d] if facing > 0 else [b, a, d, c])
    for yi in range(3):  # rim: top (+z) and bottom (-z)
        ya, yb = ys[yi], ys[yi + 1]
        quads.append([(x0, ya, zs[3]), (x1, ya, zs[3]), (x1, yb, zs[3]), (x0, yb, zs[3])])
        quads.append([(x0, ya, zs[0]), (x0, yb, zs[0]), (x1, yb, zs[0]), (x1, ya, zs[0])])
    for zi in range(3):  # rim: the -y and +y ends
        za, zb = zs[zi], zs[zi + 1]
        quads.append([(x0, ys[0], za), (x1, ys[0], za), (x1, ys[0], zb), (x0, ys[0], zb)])
        quads.append([(x0, ys[3], za), (x0, ys[3], zb), (x1, ys[3], zb), (x1, ys[3], za)])
    hy0, hy1 = hole_y
    hz0, hz1 = hole_z
    # Reveals: the inside of the hole, normals pointing into the hole.
    quads.append([(x0, hy0, hz0), (x1, hy0, hz0), (x1, hy1, hz0), (x0, hy1, hz0)])  # sill, +z
    quads.append([(x0, hy0, hz1), (x0, hy1, hz1), (x1, hy1, hz1), (x1, hy0, hz1)])  # lintel, -z
    quads.append([(x0, hy0, hz0), (x0, hy0, hz1), (x1, hy0, hz1), (x1, hy0, hz0)])  # jamb, +y
    quads.append([(x0, hy1, hz0), (x1, hy1, hz0), (x1, hy1, hz1), (x0, hy1, hz1)])  # jamb, -y
    corners = np.asarray(quads, dtype=np.float64)
    verts, inverse = np.unique(corners.reshape(-1, 3).round(12), axis=0, return_inverse=True)
    faces = inverse.reshape(-1, 4)
    return Part(name, verts, faces, quad_charts(verts, faces), albedo)


# -- the scenes -------------------------------------------------------------------------------

def _cornell_parts(subdivisions=0, bump=0.0):
    """Parts of the Cornell box; ``subdivisions > 0`` makes every face a grid (HEAVY)."""
    lo, hi, top = -0.5, 0.5, 1.0

    def wall(name, a, b, c, d, albedo):
        corners = np.array([a, b, c, d], dtype=np.float64)
        if not subdivisions:
            return _quad_part(name, corners, albedo)
        v, f = _grid(corners[0], corners[1] - corners[0], corners[3] - corners[0],
                     subdivisions, subdivisions, bump=bump)
        return Part(name, v, f, grid_uv(subdivisions, subdivisions), albedo)

    parts = [
        wall("Floor", (lo, lo, 0), (hi, lo, 0), (hi, hi, 0), (lo, hi, 0), WHITE),
        wall("Ceiling", (lo, lo, top), (lo, hi, top), (hi, hi, top), (hi, lo, top), WHITE),
        wall("BackWall", (lo, hi, 0), (hi, hi, 0), (hi, hi, top), (lo, hi, top), WHITE),
        wall("LeftWall", (lo, lo, 0), (lo, hi, 0), (lo, hi, top), (lo, lo, top), RED),
        wall("RightWall", (hi, hi, 0), (hi, lo, 0), (hi, lo, top), (hi, hi, top), GREEN),
    ]
    tall = dict(center=(-0.17, 0.12, 0.3), size=(0.3, 0.3, 0.6), angle=np.radians(17.0))
    short = dict(center=(0.17, -0.17, 0.15), size=(0.3, 0.3, 0.3), angle=np.radians(-17.0))
    if subdivisions:
        box_n = max(2, subdivisions * 2 // 3)
        parts.append(_subdivided_box_part("TallBox", albedo=WHITE, n=box_n, bump=bump * 0.3, **tall))
        parts.append(_subdivided_box_part("ShortBox", albedo=WHITE, n=box_n, bump=bump * 0.3, **short))
    else:
        parts.append(_box_part("TallBox", albedo=WHITE, **tall))
        parts.append(_box_part("ShortBox", albedo=WHITE, **short))
    lz = top - 0.005  # just below the ceiling, facing down (-z)
    lx, ly = 0.125, 0.1
    parts.append(_quad_part("Light", [(-lx, -ly, lz), (-lx, ly, lz), (lx, ly, lz), (lx, -ly, lz)],
                            emission=CORNELL_LIGHT_RADIANCE))
    return parts


#: The glossy box's floor checker: 8 x 8 squares of these two colours (linear RGB).
CHECKER_COLOURS = ((0.73, 0.73, 0.73), (0.25, 0.25, 0.25))
#: Principled inputs of the glossy box's floor and sphere.
GLOSSY_FLOOR = dict(roughness=0.2, metallic=0.0, ior=1.5, ior_level=0.5)
METAL_SPHERE = dict(roughness=0.25, metallic=1.0, ior=1.5, ior_level=0.5)
METAL_COLOUR = (0.95, 0.64, 0.54)


def floor_checker(n, colours=CHECKER_COLOURS):
    """(n², 3) colours of an n x n checker of the :func:`_grid` faces (row-major): the floor
    texture of ``GLOSSY_BOX`` as per-face colours (the hook an image texture replaces)."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    return np.asarray(colours, dtype=np.float64)[((i + j) % 2).ravel()]


def _sphere_part(name, center, radius, albedo, n=6, principled=None):
    """A sphere as a cube whose faces are n x n grids pushed onto the sphere (quads only, no
    poles), outward normals, each face of the cube its own UV chart."""
    corners = _box_corners((0.0, 0.0, 0.0), (2.0, 2.0, 2.0))
    quads = _box_faces()
    dims = quad_dims(corners, quads)
    chart_pos, chart_size = shelf_pack(dims, UV_PADDING)
    verts, faces, uvs = [], [], []
    offset = 0
    for q, (lo, size) in zip(quads, zip(chart_pos, chart_size)):
        a, b, _, d = corners[q]
        v, f = _grid(a, b - a, d - a, n, n)
        v = v / np.linalg.norm(v, axis=1, keepdims=True) * radius + np.asarray(center, dtype=np.float64)
        verts.append(v)
        faces.append(f + offset)
        uvs.append(grid_uv(n, n, lo, lo + size))
        offset += len(v)
    return Part(name, np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs), albedo,
                principled=principled)


def _glossy_box_parts():
    """The Cornell box with a glossy checkered floor and a metallic sphere for the short box."""
    parts = [p for p in _cornell_parts() if p.name not in ("Floor", "ShortBox")]
    n = 8
    v, f = _grid((-0.5, -0.5, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), n, n)
    floor = Part("Floor", v, f, grid_uv(n, n), WHITE, principled=dict(GLOSSY_FLOOR), face_albedo=floor_checker(n))
    sphere = _sphere_part("MetalSphere", (0.17, -0.17, 0.165), 0.16, METAL_COLOUR, principled=dict(METAL_SPHERE))
    return [floor] + parts[:-1] + [sphere, parts[-1]]     # the light stays last


def _narrow_opening_parts():
    """Two 1 x 1 x 1 m rooms side by side along x, joined by a 0.2 x 0.3 m hatch."""
    t = 0.1            # wall / slab thickness
    h = 1.0            # room height
    ya, yb = -0.5, 0.5  # room depth
    xa, xm, xb = -1.05, 0.0, 1.05  # outer left, dividing wall centre, outer right
    parts = []
    for room, (x0, x1) in (("RoomA", (xa + t, xm - t / 2)), ("RoomB", (xm + t / 2, xb - t))):
        cx, w = (x0 + x1) / 2, x1 - x0
        parts.append(_box_part(f"{room}Floor", (cx, 0.0, -t / 2), (w, yb - ya, t), WHITE))
        parts.append(_box_part(f"{room}Ceiling", (cx, 0.0, h + t / 2), (w, yb - ya, t), WHITE))
        parts.append(_box_part(f"{room}BackWall", (cx, yb + t / 2, h / 2), (w + 2 * t, t, h + 2 * t), WHITE))
        parts.append(_box_part(f"{room}FrontWall", (cx, ya - t / 2, h / 2), (w + 2 * t, t, h + 2 * t), WHITE))
    parts.append(_box_part("RoomASideWall", (xa + t / 2, 0.0, h / 2), (t, yb - ya, h + 2 * t), RED))
    parts.append(_box_part("RoomBSideWall", (xb - t / 2, 0.0, h / 2), (t, yb - ya, h + 2 * t), GREEN))
    parts.append(_holed_slab_part("DividingWall", (xm - t / 2, xm + t / 2), (ya, yb), (-t, h + t),
                                  hole_y=(-0.1, 0.1), hole_z=(0.25, 0.55), albedo=WHITE))
    # The only emitter: in room B, under its ceiling, nearer the dividing wall.
    lz = h - 0.005
    x0, x1, y0, y1 = 0.3, 0.55, -0.125, 0.125
    parts.append(_quad_part("Light", [(x0, y0, lz), (x0, y1, lz), (x1, y1, lz), (x1, y0, lz)],
                            emission=(120.0, 108.0, 88.0)))
    return parts


def _plane_under_sky_parts():
    return [_quad_part("Plane", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], (0.5, 0.6, 0.7))]


#: Parallel squares: receiver side, emitter side, emitter height (metres), emitter radiance.
PARALLEL_SQUARES = dict(receiver_side=1.0, emitter_side=1.0, height=1.0, radiance=(5.0, 5.0, 5.0),
                        albedo=(0.8, 0.8, 0.8))
#: Uniform world radiance of PLANE_UNDER_SKY, W / (sr m^2) per channel.
SKY_RADIANCE = (0.8, 0.9, 1.0)


def _parallel_squares_parts():
    p = PARALLEL_SQUARES
    r, e, z = p["receiver_side"] / 2, p["emitter_side"] / 2, p["height"]
    return [
        _quad_part("Receiver", [(-r, -r, 0), (r, -r, 0), (r, r, 0), (-r, r, 0)], p["albedo"]),
        _quad_part("Emitter", [(-e, -e, z), (-e, e, z), (e, e, z), (e, -e, z)], emission=p["radiance"]),
    ]


def _heavy_parts():
    return _cornell_parts(subdivisions=110, bump=0.01)


_BUILDERS = {
    "CORNELL_BOX": _cornell_parts,
    "NARROW_OPENING": _narrow_opening_parts,
    "PLANE_UNDER_SKY": _plane_under_sky_parts,
    "PARALLEL_SQUARES": _parallel_squares_parts,
    "HEAVY": _heavy_parts,
    "GLOSSY_BOX": _glossy_box_parts,
}

_CAMERAS = {
    "CORNELL_BOX": CameraView((0.0, -1.85, 0.5), (0.0, 0.0, 0.5), np.radians(39.3)),
    "HEAVY": CameraView((0.0, -1.85, 0.5), (0.0, 0.0, 0.5), np.radians(39.3)),
    "GLOSSY_BOX": CameraView((0.0, -1.85, 0.5), (0.0, 0.0, 0.5), np.radians(39.3)),
    # Looking into room A through its (invisible from outside) front wall would hide everything:
    # the camera sits inside room A, in its front-left corner, looking at the hatch.
    "NARROW_OPENING": CameraView((-0.9, -0.42, 0.75), (0.0, 0.0, 0.4), np.radians(70.0)),
    "PLANE_UNDER_SKY": CameraView((0.0, -3.0, 2.0), (0.0, 0.0, 0.0), np.radians(39.3)),
    "PARALLEL_SQUARES": CameraView((2.2, -2.2, 1.2), (0.0, 0.0, 0.5), np.radians(39.3)),
}


def check_kind(kind):
    """Return the canonical scene kind for ``kind`` (case-insensitive) or raise SceneError."""
    key = str(kind).upper()
    if key not in _BUILDERS:
        raise SceneError(f"Unknown demo scene '{kind}': choose one of {', '.join(SCENE_KINDS)}")
    return key


def scene_parts(kind):
    """The parts (:class:`Part`) of the built-in scene ``kind``, in a fixed order."""
    return _BUILDERS[check_kind(kind)]()


def world_radiance(kind):
    """(3,) uniform world radiance of scene ``kind`` (black except PLANE_UNDER_SKY)."""
    if check_kind(kind) == "PLANE_UNDER_SKY":
        return np.array(SKY_RADIANCE, dtype=np.float64)
    return np.zeros(3)


def camera_view(kind):
    """The :class:`CameraView` the demo camera uses for scene ``kind``."""
    return _CAMERAS[check_kind(kind)]


def state_part_names(kind):
    """Names of the parts that carry states by default: every part that is not an emitter."""
    return [p.name for p in scene_parts(kind) if not p.is_emitter]


def parts_to_scene_arrays(parts, selected=None, world=(0.0, 0.0, 0.0)):
    """Concatenate parts into :class:`SceneArrays`.

    ``selected``: names of the parts that carry states (None: every non-emitting part). Triangles
    are in part order, two per quad (see :attr:`Part.triangles`).
    """
    names = [p.name for p in parts]
    if selected is None:
        selected = [p.name for p in parts if not p.is_emitter]
    selected = list(selected)
    unknown = [s for s in selected if s not in names]
    if unknown:
        raise SceneError(f"No part named {', '.join(map(repr, unknown))} in this scene: "
                         f"its parts are {', '.join(names)}")
    verts, tris, obj, albedo, emission, two_sided, uv, material = [], [], [], [], [], [], [], []
    lobes, lobe_names = [], []
    offset = 0
    for i, p in enumerate(parts):
        t = p.triangles
        verts.append(p.vertices)
        tris.append(t + offset)
        offset += len(p.vertices)
        obj.append(np.full(len(t), i, dtype=np.int32))
        albedo.append(p.triangle_albedo)
        colours, face_colour = p.base_colours
        index = np.full(len(colours), -1, np.int32)
        for c, colour in enumerate(colours):
            if p.lobes(colour):
                index[c] = len(lobes)
                lobes.append(p.lobes(colour))
                lobe_names.append(f"{p.name} {c}")
        material.append(np.repeat(index[face_colour], 2))
        emission.append(np.broadcast_to(p.emission, (len(t), 3)))
        two_sided.append(np.full(len(t), p.two_sided_emission))
        uv.append(p.uv)
    return SceneArrays(
        vertices=np.concatenate(verts),
        triangles=np.concatenate(tris),
        triangle_object=np.concatenate(obj),
        triangle_albedo=np.concatenate(albedo),
        triangle_emission=np.concatenate(emission),
        object_names=names,
        object_carries_states=np.array([n in selected for n in names]),
        world_radiance=np.asarray(world, dtype=np.float32),
        triangle_emission_two_sided=np.concatenate(two_sided),
        triangle_uv=np.concatenate(uv),
        object_has_uv=np.ones(len(parts), dtype=bool),
        triangle_material=np.concatenate(material) if lobes else None,
        materials=bsdf.MaterialTable.from_lobes(lobes, lobe_names) if lobes else None,
    )


def build_scene_arrays(kind, selected=None):
    """:class:`SceneArrays` of the built-in scene ``kind``.

    ``selected``: names of the parts that carry states; None selects every non-emitting part.
    """
    return parts_to_scene_arrays(scene_parts(kind), selected, world_radiance(kind))
