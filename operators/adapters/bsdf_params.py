"""The microfacet lobes of node materials: Principled specular and metallic, the Glossy BSDF.

:func:`material_lobes` walks a material's surface shader as Cycles' SVM sets up its closures
(``svm_node_closure_bsdf``) and returns the lobes :class:`~lmdp_addon.bsdf.MaterialTable` takes:

* Principled BSDF (v2, Blender 4+): Metallic > 0 gives a CONDUCTOR lobe (weight Metallic, F82-tint
  Fresnel, F0 = Base Color, tint = Specular Tint); the specular layer a DIELECTRIC lobe (weight
  (1 - Metallic)(1 - Transmission), η and F0 from IOR and Specular IOR Level, F0 x Specular Tint)
  over the diffuse base, unless its η is 1 (Specular IOR Level 0); α = Roughness²; the
  distribution (GGX / Multiscatter GGX) as set on the node;
* Glossy BSDF: a GLOSSY lobe of weight Color (GGX or Multiscatter GGX; Beckmann and
  Ashikhmin-Shirley are read as GGX, with a warning);
* Mix Shader / Add Shader: the lobes of both inputs with their factors.

The diffuse part (Base Color x (1 - Metallic) x (1 - Transmission), Diffuse BSDF) stays where
``extract`` reads it: ``SceneArrays.triangle_albedo``. What is not modelled (coat, sheen,
anisotropy, transmission) is named in one warning per material and node.
"""
import numpy as np

from ...lmdp_addon import bsdf

#: Glossy BSDF distributions read as GGX (single-scatter) with a warning.
_OTHER_DISTRIBUTIONS = {'BECKMANN': "Beckmann", 'ASHIKHMIN_SHIRLEY': "Ashikhmin-Shirley"}


def _finite(reader, node, owner, name, value, default):
    """``value`` where it is finite, else ``default`` with a warning naming the input."""
    value = np.asarray(value, dtype=np.float64)
    if np.all(np.isfinite(value)):
        return value if value.ndim else float(value)
    reader.warn(f"{owner}: '{node.name}' {name} is not a finite number; LMDP uses {np.round(default, 3)}")
    return default


def _value(reader, node, owner, name, default):
    return _finite(reader, node, owner, name, reader.value(node, name, owner), default)


def _colour(reader, node, owner, name, default):
    return _finite(reader, node, owner, name, reader.colour(node, name, owner), np.full(3, default))


def _principled(reader, node, owner, scale):
    for name in ("Coat Weight", "Sheen Weight", "Anisotropic", "Thin Film Thickness"):
        if name in node.inputs and _value(reader, node, owner, name, 0.0) > 0:
            reader.warn(f"{owner}: Principled BSDF '{node.name}' {name} {reader.value(node, name, owner):g} is "
                        "not modelled (LMDP keeps its diffuse, specular and metallic parts)")
    tint = _colour(reader, node, owner, "Specular Tint", 1.0) if "Specular Tint" in node.inputs else np.ones(3)
    metallic = _value(reader, node, owner, "Metallic", 0.0)
    # Base Color is the conductor's F0 only (the diffuse colour at a point is shading.py's): read
    # (and warn about a texture there) only when the material is metallic.
    base = _colour(reader, node, owner, "Base Color", 0.8) if metallic > 0 else np.full(3, 0.8)
    return bsdf.principled_lobes(base, metallic,
                                 _value(reader, node, owner, "Roughness", 0.5),
                                 _value(reader, node, owner, "IOR", 1.5),
                                 _value(reader, node, owner, "Specular IOR Level", 0.5), tint,
                                 _value(reader, node, owner, "Transmission Weight", 0.0),
                                 multiscatter=getattr(node, "distribution", 'MULTI_GGX') == 'MULTI_GGX',
                                 scale=scale)


def _glossy(reader, node, owner, scale):
    colour = np.maximum(_colour(reader, node, owner, "Color", 0.8), 0.0)
    roughness = float(np.clip(_value(reader, node, owner, "Roughness", 0.5), 0.0, 1.0))
    distribution = getattr(node, "distribution", 'MULTI_GGX')
    if distribution in _OTHER_DISTRIBUTIONS:
        reader.warn(f"{owner}: Glossy BSDF '{node.name}' uses the {_OTHER_DISTRIBUTIONS[distribution]} "
                    "distribution; LMDP reflects it as GGX of the same roughness")
    if "Anisotropy" in node.inputs and abs(_value(reader, node, owner, "Anisotropy", 0.0)) > 1e-4:
        reader.warn(f"{owner}: Glossy BSDF '{node.name}' anisotropy is not modelled (isotropic GGX)")
    return [dict(kind=bsdf.GLOSSY, weight=scale * colour, roughness=roughness,
                 multiscatter=distribution == 'MULTI_GGX')]


def shader_lobes(reader, socket, owner, scale=1.0, depth=0):
    """The microfacet lobes (dicts, see ``MaterialTable.from_lobes``) of the shader feeding
    ``socket``, their weights multiplied by ``scale``; ``reader``: extract's material reader
    (socket values and warnings)."""
    source = reader._source(socket)
    if source is None or depth > 32 or np.all(np.asarray(scale) <= 0):
        return []
    node, _ = source
    if node.type == 'BSDF_PRINCIPLED':
        return _principled(reader, node, owner, scale)
    if node.type == 'BSDF_GLOSSY':
        return _glossy(reader, node, owner, scale)
    if node.type == 'MIX_SHADER':
        if not (_has_lobes(reader, node.inputs[1], depth + 1) or _has_lobes(reader, node.inputs[2], depth + 1)):
            return []    # no lobe below: its factor is shading.py's alone
        fac = min(max(reader.value(node, "Fac", owner), 0.0), 1.0)
        return (shader_lobes(reader, node.inputs[1], owner, scale * (1.0 - fac), depth + 1)
                + shader_lobes(reader, node.inputs[2], owner, scale * fac, depth + 1))
    if node.type == 'ADD_SHADER':
        return (shader_lobes(reader, node.inputs[0], owner, scale, depth + 1)
                + shader_lobes(reader, node.inputs[1], owner, scale, depth + 1))
    return []


def _has_lobes(reader, socket, depth=0):
    """True when a Principled or Glossy BSDF feeds ``socket`` through Mix / Add Shaders."""
    source = reader._source(socket)
    if source is None or depth > 32:
        return False
    node = source[0]
    if node.type in ('BSDF_PRINCIPLED', 'BSDF_GLOSSY'):
        return True
    if node.type == 'MIX_SHADER':
        return _has_lobes(reader, node.inputs[1], depth + 1) or _has_lobes(reader, node.inputs[2], depth + 1)
    if node.type == 'ADD_SHADER':
        return _has_lobes(reader, node.inputs[0], depth + 1) or _has_lobes(reader, node.inputs[1], depth + 1)
    return False


def material_lobes(reader, mat):
    """The microfacet lobes of material ``mat`` (None or without nodes: none), at most
    :data:`~lmdp_addon.bsdf.MAX_LOBES` (a warning names the material when there are more, or
    when more than one specular layer covers its diffuse part)."""
    tree = getattr(mat, "node_tree", None)
    if mat is None or tree is None:
        return []
    output = tree.get_output_node('CYCLES')
    if output is None:
        return []
    owner = f"Material '{mat.name}'"
    lobes = shader_lobes(reader, output.inputs["Surface"], owner)
    if len(lobes) > bsdf.MAX_LOBES:
        reader.warn(f"{owner}: {len(lobes)} glossy / specular lobes; LMDP keeps the first {bsdf.MAX_LOBES}")
        lobes = lobes[:bsdf.MAX_LOBES]
    if sum(bool(lobe.get("layer")) for lobe in lobes) > 1:
        reader.warn(f"{owner}: several Principled specular layers; the diffuse part is weighted under "
                    "the first one only")
    return lobes


def cycles_glossy_settings(scene, arrays):
    """The Cycles settings of ``scene`` that change how its glossy surfaces (``arrays.has_glossy()``)
    bake: Filter Glossy (``blur_glossy``) goes into ``arrays.materials.filter_glossy`` (Cycles
    roughens glossy lobes after a diffuse bounce, and so does the tracer); returns a warning for
    what is not followed: Reflective Caustics off (Cycles drops glossy lobes after a diffuse
    bounce). (Glossy and Max bounces reach the tracer through ``LightPaths``.)"""
    cycles = getattr(scene, "cycles", None)
    if cycles is None or not arrays.has_glossy():
        return []
    arrays.materials.filter_glossy = max(float(cycles.blur_glossy), 0.0)
    out = []
    if not cycles.caustics_reflective:
        out.append("Cycles' Reflective Caustics is off: Cycles' bakes drop glossy reflections after the "
                   "texel's diffuse bounce; LMDP keeps them")
    return out
