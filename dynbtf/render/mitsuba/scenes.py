"""Example Mitsuba scenes for a synthesized BTF, built procedurally (no files, no downloads).

Three geometries x two lighting conditions (as in the paper's teaser):

=========  ============================================================================
scene      what it shows
=========  ============================================================================
plane      a 40 x 40 ground plane seen at a grazing angle: the view that exposes
           repetition (tiling shows a grid of copies towards the horizon)
sphere     a unit sphere on a grey floor: every view and light angle at once
cloth      a procedurally draped sheet (folds over a bump): a curved, cloth-like surface
=========  ============================================================================

``lighting="point"``: a point light up and to the side plus a dim constant
environment; ``lighting="sky"``: a procedural sky environment map (blue zenith,
warm horizon, a soft sun), importance-sampled by Mitsuba's ``envmap``.

World space is z-up. The material's ``scale`` is the number of exemplar repeats
across the mesh's uv range (the plane's and cloth's uv span the whole mesh, the
sphere's ``u`` runs around the equator).
"""

from __future__ import annotations

import math

import numpy as np

from ...errors import InputError
from ...jit import mi_module

__all__ = ["SCENES", "LIGHTINGS", "scene_dict", "bsdf_dict", "sky_bitmap", "cloth_mesh"]

SCENES = ("plane", "sphere", "cloth")
LIGHTINGS = ("point", "sky")


def bsdf_dict(model_path, *, method: str = "auto", scale: float = 1.0, seed: int = 0,
              scale_v: float | None = None, sampling: str | None = None) -> dict:
    """The ``dynbtf`` BSDF as a Mitsuba dict (see :data:`dynbtf.render.mitsuba.bsdf.PLUGIN_DOC`).

    ``method``: ``tile``, ``hist``, ``hex``, ``struct`` or ``auto`` (``struct`` or ``hist``, chosen by the plugin).

    ``sampling`` (``"auto"``, ``"mixture"`` or ``"cosine"``) is left to the plugin's default when ``None``.
    """
    d = {"type": "dynbtf", "filename": str(model_path), "method": str(method), "scale": float(scale),
         "seed": int(seed)}
    if scale_v is not None:
        d["scale_v"] = float(scale_v)
    if sampling is not None:
        d["sampling"] = str(sampling)
    return d


def sky_bitmap(width: int = 256, height: int = 128, *, sun_elevation: float = 35.0, sun_azimuth: float = -60.0):
    """A procedural HDR sky as a float32 ``(height, width, 3)`` lat-long array (y-up, Mitsuba's envmap layout).

    Blue zenith fading to a warm, brighter horizon, a dark-grey ground half, and
    a soft sun disk (``sun_elevation`` / ``sun_azimuth`` in degrees).
    """
    v = (np.arange(height) + 0.5) / height        # 0 = zenith (+y), 1 = nadir
    u = (np.arange(width) + 0.5) / width
    theta = v * math.pi
    phi = u * 2.0 * math.pi
    elev = 0.5 * math.pi - theta                 # elevation above the horizon
    zenith = np.array([0.25, 0.45, 0.95], dtype=np.float32)
    horizon = np.array([1.0, 0.85, 0.70], dtype=np.float32)
    ground = np.array([0.18, 0.17, 0.16], dtype=np.float32)
    t = np.clip(np.sin(np.maximum(elev, 0.0)), 0.0, 1.0) ** 0.5
    sky = (1.0 - t)[:, None] * horizon + t[:, None] * zenith
    img = np.where((elev > 0.0)[:, None], sky, ground)[:, None, :].repeat(width, axis=1)
    # sun: direction in Mitsuba's envmap frame (y up); a Gaussian lobe plus a bright core
    se, sa = math.radians(sun_elevation), math.radians(sun_azimuth)
    sun = np.array([math.cos(se) * math.sin(sa), math.sin(se), -math.cos(se) * math.cos(sa)])
    dirs = np.stack([np.sin(theta)[:, None] * np.sin(phi)[None, :],
                     np.cos(theta)[:, None] * np.ones_like(phi)[None, :],
                     -np.sin(theta)[:, None] * np.cos(phi)[None, :]], axis=-1)
    cosang = dirs @ sun
    img = img + (300.0 * np.exp((cosang - 1.0) / 0.0015))[..., None] * np.array([1.0, 0.93, 0.8])
    img = img + (1.5 * np.exp((cosang - 1.0) / 0.05))[..., None] * np.array([1.0, 0.9, 0.7])
    return img.astype(np.float32)


def cloth_mesh(bsdf, *, resolution: int = 160, size: float = 3.0):
    """A draped sheet: a ``size x size`` grid over a bump with radial folds, as an ``mi.Mesh``.

    uv follows the sheet's undeformed grid (``[0, 1]^2``), so texels stay nearly
    square where the surface is not steep; smooth vertex normals come from the
    analytic height-field gradient.
    """
    mi = mi_module()
    n = int(resolution)
    s = np.linspace(-0.5, 0.5, n + 1)
    x, y = np.meshgrid(s * size, s * size)
    r = np.sqrt(x ** 2 + y ** 2)
    ang = np.arctan2(y, x)

    def height(x, y):
        r = np.sqrt(x ** 2 + y ** 2)
        a = np.arctan2(y, x)
        drape = 0.9 * np.exp(-(r / 0.9) ** 2)
        folds = 0.09 * np.sin(7.0 * a + 1.5 * r) * np.clip(r / 0.8, 0.0, 1.0) * np.exp(-((r - 1.0) / 0.9) ** 2)
        return 0.12 + drape + folds  # lifted: the folds' troughs stay above the floor

    z = height(x, y)
    eps = 1e-4
    dzdx = (height(x + eps, y) - height(x - eps, y)) / (2 * eps)
    dzdy = (height(x, y + eps) - height(x, y - eps)) / (2 * eps)
    normals = np.stack([-dzdx, -dzdy, np.ones_like(z)], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    del r, ang
    positions = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    uv = np.stack(np.meshgrid((s + 0.5), (s + 0.5)), -1).reshape(-1, 2).astype(np.float32)
    idx = np.arange((n + 1) ** 2, dtype=np.uint32).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], 2).reshape(-1, 3)
    props = mi.Properties()
    props["bsdf"] = bsdf
    mesh = mi.Mesh("cloth", len(positions), len(faces), props, has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.ravel())
    params["vertex_normals"] = mi.Float(normals.astype(np.float32).ravel())
    params["vertex_texcoords"] = mi.Float(uv.ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    return mesh


def _look_at(mi, origin, target, up=(0.0, 0.0, 1.0)):
    return mi.ScalarTransform4f().look_at(origin=list(origin), target=list(target), up=list(up))


def scene_dict(scene: str, material: dict, *, lighting: str = "sky", resolution=(512, 512), spp: int = 16,
               max_depth: int = 3, seed: int = 0, footprint_spp: int | None = None) -> dict:
    """A Mitsuba scene dict: ``scene`` geometry covered by ``material`` under ``lighting``.

    Parameters
    ----------
    scene : {"plane", "sphere", "cloth"}
    material : dict
        A BSDF dict, normally :func:`bsdf_dict` (for the sphere, ``scale_v`` is
        set to half of ``scale`` unless given, so texels are square at the equator;
        a ``dynbtf`` material gets the camera's ``ray_cone_angle`` for its footprints
        unless given: :func:`dynbtf.render.mitsuba.bsdf.ray_cone_angle` of the
        scene's field of view, width and ``footprint_spp``).
    lighting : {"point", "sky"}
    resolution : (height, width)
    spp : int
        Samples per pixel of one ``mi.render`` call.
    max_depth : int
        Path length (3 = direct light plus one bounce).
    seed : int
        Sampler seed.
    footprint_spp : int, optional
        Samples per pixel that the material's footprints stand for (default ``spp``; the total of
        all passes when several renders are averaged).
    """
    mi = mi_module()
    if scene not in SCENES:
        raise InputError(f"scene: expected one of {list(SCENES)}, got {scene!r}")
    if lighting not in LIGHTINGS:
        raise InputError(f"lighting: expected one of {list(LIGHTINGS)}, got {lighting!r}")
    height, width = int(resolution[0]), int(resolution[1])
    fov = {"plane": 45.0, "sphere": 32.0, "cloth": 38.0}[scene]  # degrees along the image's width
    if material.get("type") == "dynbtf" and "ray_cone_angle" not in material:
        from .bsdf import ray_cone_angle

        material = {**material, "ray_cone_angle": ray_cone_angle(fov, width, spp if footprint_spp is None
                                                                  else footprint_spp)}
    film = {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
            "pixel_format": "rgb"}
    sampler = {"type": "independent", "sample_count": int(spp), "seed": int(seed)}
    floor_bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.35, 0.35, 0.35]}}
    d: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth), "hide_emitters": False}}
    if scene == "plane":
        d["sensor"] = {"type": "perspective", "fov": fov, "fov_axis": "x",
                       "to_world": _look_at(mi, (0.0, -19.0, 1.4), (0.0, 4.0, -1.2)), "film": film, "sampler": sampler}
        d["surface"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([20.0, 20.0, 1.0]),
                        "bsdf": dict(material)}
        light_pos, light_power = (3.0, -8.0, 9.0), 220.0
    elif scene == "sphere":
        mat = dict(material)
        if mat.get("type") == "dynbtf" and "scale_v" not in mat:
            mat["scale_v"] = 0.5 * float(mat.get("scale", 1.0))
        d["sensor"] = {"type": "perspective", "fov": fov, "fov_axis": "x",
                       "to_world": _look_at(mi, (0.0, -5.2, 2.6), (0.0, 0.0, 0.85)), "film": film, "sampler": sampler}
        d["surface"] = {"type": "sphere", "center": [0.0, 0.0, 1.0], "radius": 1.0, "bsdf": mat}
        d["floor"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([8.0, 8.0, 1.0]),
                      "bsdf": floor_bsdf}
        light_pos, light_power = (3.0, -3.0, 5.0), 60.0
    else:
        bsdf = mi.load_dict(dict(material))
        d["sensor"] = {"type": "perspective", "fov": fov, "fov_axis": "x",
                       "to_world": _look_at(mi, (0.0, -4.2, 3.0), (0.0, 0.0, 0.3)), "film": film, "sampler": sampler}
        d["surface"] = cloth_mesh(bsdf)
        d["floor"] = {"type": "rectangle",
                      "to_world": mi.ScalarTransform4f().translate([0.0, 0.0, -0.01]).scale([8.0, 8.0, 1.0]),
                      "bsdf": floor_bsdf}
        light_pos, light_power = (2.5, -2.5, 4.5), 45.0
    if lighting == "point":
        d["light"] = {"type": "point", "position": list(light_pos),
                      "intensity": {"type": "rgb", "value": [light_power] * 3}}
        d["ambient"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.04, 0.045, 0.055]}}
    else:
        d["sky"] = {"type": "envmap", "bitmap": mi.Bitmap(sky_bitmap()), "scale": 1.0,
                    "to_world": mi.ScalarTransform4f().rotate([1.0, 0.0, 0.0], 90.0)}
    return d
