"""``ns-gsticker-scene``: render a small textured multi-object demo scene as a Nerfstudio dataset.

``--layout object`` (default): the scene (or a user's own mesh) seen from cameras on the upper hemisphere, radius 4,
looking at the origin, in the layout of Nerfstudio's ``blender-data`` dataparser: ``transforms_{train,val,test}.json``
plus RGBA PNGs (alpha: the object's coverage) and a float32 OpenEXR z-depth map per view.
``--layout capture``: a forward-facing handheld-style capture of the same scene in front of a wall and on a floor
(every pixel sees something; RGB PNGs), cameras on a small arc, in the ``nerfstudio-data`` layout: one
``transforms.json`` with OpenCV-style intrinsics and ``train/val/test_filenames``.

Over 600 lines on purpose: both layouts share the scene's meshes, textures, ray tracer and writers; split, each half
would import the other.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
import tyro
from jaxtyping import Float, Int, UInt8
from tqdm import tqdm

from gsticker_plugin.errors import GStickerError, print_error, run_command

CAMERA_RADIUS = 4.0
"""Distance of every camera from the origin."""
NEAR, FAR = 2.0, 6.0
"""Blender-style near/far planes; all visible geometry lies between them."""
SCENE_RADIUS = 1.2
"""Every vertex lies within this distance of the origin (so inside the default [-1.5, 1.5]^3 box)."""
CAMERA_ANGLE_X = 0.6911112070083618
"""Horizontal field of view in radians (that of the original Blender synthetic scenes)."""
CAPTURE_CENTER = (0.0, -3.6, 1.2)
"""``--layout capture``: the middle of the camera trajectory; cameras look toward the origin from there."""
CAPTURE_SPREAD = (1.2, 0.35, 0.35)
"""``--layout capture``: half-extent (x, y, z) of the box the camera positions are drawn from."""
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tga", ".bmp", ".tif", ".tiff", ".exr", ".webp")
SPLITS = ("train", "val", "test")


class SceneError(GStickerError):
    """A problem with the user's input; the message is one line naming the problem and its fix."""


@dataclass
class SceneConfig:
    """Render a textured multi-object demo scene (or your own mesh) as a Nerfstudio blender-data dataset."""

    output_dir: Path = Path("data/gsticker-scene")
    """Folder to write the dataset to (written to a temporary sibling and renamed when complete)."""
    resolution: int = 100
    """Width and height of every rendered image, in pixels."""
    num_train: int = 100
    """Number of training views."""
    num_val: int = 20
    """Number of validation views."""
    num_test: int = 50
    """Number of test views."""
    seed: int = 0
    """Seed for the camera poses; the same seed and settings give byte-identical files."""
    mesh: Optional[Path] = None
    """Your own mesh instead of the built-in scene: an .obj/.ply/.glb/.gltf/.off/.stl file or a folder holding one."""
    mesh_up: Literal["y", "z"] = "y"
    """Up axis of --mesh (.obj/.glb files are usually y-up); the dataset is z-up like Blender."""
    layout: Literal["object", "capture"] = "object"
    """object: a Blender-format turntable dataset (transparent background); capture: a forward-facing capture with
    a wall and floor behind the scene, in the nerfstudio-data format (transforms.json)."""
    supersample: int = 3
    """Render at this many times the resolution and average down, giving soft alpha edges."""
    overwrite: bool = False
    """Replace --output-dir if it already holds a dataset."""


@dataclass(frozen=True)
class Part:
    """One renderable piece: a triangle mesh with a flat color, per-vertex colors, or a texture."""

    vertices: Float[np.ndarray, "v 3"]
    faces: Int[np.ndarray, "f 3"]
    color: Tuple[float, float, float] = (0.8, 0.8, 0.8)
    normals: Optional[Float[np.ndarray, "v 3"]] = None
    uv: Optional[Float[np.ndarray, "v 2"]] = None
    texture: Optional[UInt8[np.ndarray, "h w 3"]] = None
    vertex_colors: Optional[UInt8[np.ndarray, "v 3"]] = None


# ----------------------------------------------------------------------------- cameras


def look_at(position: Float[np.ndarray, "3"], up: Sequence[float] = (0.0, 0.0, 1.0)) -> Float[np.ndarray, "4 4"]:
    """Camera-to-world matrix (OpenGL/Blender convention: the camera looks down -z, y is up) facing the origin."""
    back = position / np.linalg.norm(position)
    right = np.cross(np.asarray(up, dtype=np.float64), back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, position
    return c2w


def sample_camera_poses(
    num: int,
    rng: np.random.Generator,
    radius: float = CAMERA_RADIUS,
    min_elevation_deg: float = 5.0,
    max_elevation_deg: float = 80.0,
) -> Float[np.ndarray, "n 4 4"]:
    """``num`` cameras uniformly (by area) on a band of the upper hemisphere, all looking at the origin."""
    lo, hi = math.sin(math.radians(min_elevation_deg)), math.sin(math.radians(max_elevation_deg))
    draws = rng.random((num, 2))  # one (height, azimuth) pair per camera: more views extend, not reshuffle
    z, azimuth = lo + (hi - lo) * draws[:, 0], 2.0 * math.pi * draws[:, 1]
    ring = np.sqrt(1.0 - z**2)
    positions = radius * np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=-1)
    return np.stack([look_at(p) for p in positions]) if num else np.zeros((0, 4, 4))


def sample_capture_poses(num: int, rng: np.random.Generator) -> Float[np.ndarray, "n 4 4"]:
    """``num`` forward-facing cameras: positions in a box around :data:`CAPTURE_CENTER`, each looking at a point
    near the origin (a handheld sweep in front of the scene)."""
    draws = rng.random((num, 5)) * 2.0 - 1.0
    out = []
    for d in draws:
        pos = np.asarray(CAPTURE_CENTER) + np.asarray(CAPTURE_SPREAD) * d[:3]
        target = np.array([0.25 * d[3], 0.0, -0.2 + 0.1 * d[4]])
        c2w = look_at(pos - target)
        c2w[:3, 3] = pos
        out.append(c2w)
    return np.stack(out) if num else np.zeros((0, 4, 4))


def split_poses(
    seed: int, counts: Dict[str, int], layout: Literal["object", "capture"] = "object"
) -> Dict[str, Float[np.ndarray, "n 4 4"]]:
    """Poses per split, each split from its own child stream so changing one count leaves the others alone."""
    streams = np.random.SeedSequence(seed).spawn(len(SPLITS))
    sample = sample_camera_poses if layout == "object" else sample_capture_poses
    return {s: sample(counts[s], np.random.default_rng(st)) for s, st in zip(SPLITS, streams)}


# ----------------------------------------------------------------------------- scene assembly


def _unmerged(mesh) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-corner vertices, faces and smooth normals of a trimesh (so UV seams can be cut per triangle)."""
    faces = np.asarray(mesh.faces)
    verts = np.asarray(mesh.vertices)[faces].reshape(-1, 3)
    normals = np.asarray(mesh.vertex_normals)[faces].reshape(-1, 3)
    return verts, np.arange(len(verts)).reshape(-1, 3), normals


def _angular_u(points: Float[np.ndarray, "v 3"], center: Float[np.ndarray, "3"]) -> Float[np.ndarray, " v"]:
    """Azimuthal texture coordinate in [0, 1], unwrapped per triangle so no triangle spans the seam."""
    d = points - center
    u = (np.arctan2(d[:, 1], d[:, 0]) / (2 * math.pi) + 0.5).reshape(-1, 3)
    wraps = (u.max(axis=1) - u.min(axis=1)) > 0.5
    u[wraps] = np.where(u[wraps] < 0.5, u[wraps] + 1.0, u[wraps])
    return u.reshape(-1)


def _textured(mesh, texture: np.ndarray, kind: Literal["sphere", "cylinder", "plane"]) -> Part:
    """A Part with procedural texture coordinates (spherical, cylindrical or top-down planar)."""
    verts, faces, normals = _unmerged(mesh)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    center = (lo + hi) / 2
    if kind == "plane":
        uv = (verts[:, :2] - lo[:2]) / (hi[:2] - lo[:2])
    else:
        if kind == "sphere":
            d = verts - center
            v = 0.5 + np.arcsin(np.clip(d[:, 2] / np.linalg.norm(d, axis=1), -1, 1)) / math.pi
        else:
            v = (verts[:, 2] - lo[2]) / (hi[2] - lo[2])
        uv = np.stack([_angular_u(verts, center), v], axis=-1)
    return Part(verts, faces, normals=normals if kind == "sphere" else None, uv=uv, texture=texture)


def _solid(mesh, color: Tuple[float, float, float], smooth: bool) -> Part:
    """A flat-colored Part; smooth parts keep their averaged vertex normals, others shade per face."""
    verts, faces, normals = _unmerged(mesh)
    return Part(verts, faces, color=color, normals=normals if smooth else None)


def builtin_scene() -> List[Part]:
    """The demo scene: a textured plate carrying red, green and blue primitives and two textured ones."""
    # deferred: the scene generator's textures
    import skimage.data
    import trimesh
    from trimesh.transformations import rotation_matrix, translation_matrix

    def placed(mesh, xyz, angle=0.0, axis=(0, 0, 1)):
        mesh.apply_transform(translation_matrix(xyz) @ rotation_matrix(angle, axis))
        return mesh

    plate = placed(trimesh.creation.cylinder(radius=1.05, height=0.1, sections=96), (0, 0, -0.55))
    return [
        _textured(plate, skimage.data.coffee(), "plane"),
        _solid(placed(trimesh.creation.icosphere(4, radius=0.32), (0.5, 0.5, -0.18)), (0.85, 0.08, 0.08), True),
        _solid(
            placed(trimesh.creation.torus(0.3, 0.11, 64, 24), (-0.52, 0.42, -0.08), math.pi / 2, (1, 0, 0)),
            (0.1, 0.75, 0.15),
            True,
        ),
        _solid(
            placed(trimesh.creation.box((0.48, 0.48, 0.48)), (0.5, -0.48, -0.26), math.radians(30)),
            (0.1, 0.2, 0.9),
            False,
        ),
        _textured(
            placed(trimesh.creation.icosphere(4, radius=0.33), (-0.5, -0.5, -0.17)), skimage.data.astronaut(), "sphere"
        ),
        _textured(
            placed(trimesh.creation.cylinder(radius=0.2, height=0.75, sections=64), (0, 0, -0.125)),
            skimage.data.chelsea(),
            "cylinder",
        ),
    ]


def capture_backdrop() -> List[Part]:
    """``--layout capture``: a textured wall behind the scene and a floor under it, large enough that every view of
    :func:`sample_capture_poses` sees only geometry."""
    # deferred: the scene generator's textures
    import skimage.data

    def quad(corners: np.ndarray, texture: np.ndarray, repeat: Tuple[float, float]) -> Part:
        verts = np.asarray(corners, dtype=np.float64)
        uv = np.array([[0.0, 0.0], [repeat[0], 0.0], [repeat[0], repeat[1]], [0.0, repeat[1]]])
        return Part(verts, np.array([[0, 1, 2], [0, 2, 3]]), uv=uv, texture=texture)

    brick = np.stack([skimage.data.brick()] * 3, axis=-1)
    brick = (brick.astype(np.float64) * np.array([1.0, 0.8, 0.65])).astype(np.uint8)
    gravel = np.stack([skimage.data.gravel()] * 3, axis=-1)
    gravel = (gravel.astype(np.float64) * np.array([0.7, 0.8, 0.7])).astype(np.uint8)
    wall = quad(np.array([[-8.0, 2.5, -0.6], [8.0, 2.5, -0.6], [8.0, 2.5, 6.0], [-8.0, 2.5, 6.0]]), brick, (4, 1.6))
    floor = quad(np.array([[-8.0, -9.0, -0.6], [8.0, -9.0, -0.6], [8.0, 2.5, -0.6], [-8.0, 2.5, -0.6]]), gravel, (4, 3))
    return [wall, floor]


def read_texture(path: Path) -> UInt8[np.ndarray, "h w 3"]:
    """Read an image file as 8-bit RGB with OpenImageIO, or raise SceneError."""
    # deferred: native image library, only image I/O needs it
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    pixels = None if buf.has_error else buf.get_pixels(oiio.UINT8)
    if pixels is None or pixels.size == 0 or buf.has_error:
        reason = (buf.geterror() or "unknown format").strip().splitlines()[0]
        raise SceneError(f"texture {path} cannot be read ({reason}); replace it with a valid PNG/JPEG or remove it")
    pixels = np.asarray(pixels).reshape(buf.spec().height, buf.spec().width, -1)
    return np.ascontiguousarray(np.repeat(pixels[..., :1], 3, -1) if pixels.shape[2] < 3 else pixels[..., :3])


def resolve_mesh_file(path: Path) -> Path:
    """The mesh file named by --mesh (a file, or the one mesh file inside a folder), or raise SceneError."""
    hint = "pass --mesh with a path to an .obj/.ply/.glb (or a folder holding one) or omit it for the built-in scene"
    if not path.exists():
        raise SceneError(f"mesh path {path} does not exist; {hint}")
    if path.is_dir():
        found = sorted(p for p in path.iterdir() if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
        if len(found) != 1:
            what = "no mesh file" if not found else f"{len(found)} mesh files ({', '.join(p.name for p in found)})"
            raise SceneError(f"folder {path} holds {what}; {hint}")
        return found[0]
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise SceneError(f"mesh file {path} has an unsupported type {path.suffix!r}; {hint}")
    return path


def obj_texture_files(obj: Path) -> List[Path]:
    """Texture images an .obj references through its .mtl files; raises SceneError if one is missing."""
    found: List[Path] = []
    for line in obj.read_text(errors="replace").splitlines():
        if line.startswith("mtllib "):
            mtl = obj.parent / line.split(None, 1)[1].strip()
            if not mtl.is_file():
                raise SceneError(
                    f"material file {mtl} named by {obj} does not exist; put it next to the .obj "
                    "or delete the mtllib line"
                )
            for mline in mtl.read_text(errors="replace").splitlines():
                if mline.strip().startswith("map_Kd"):
                    found.append(mtl.parent / mline.split()[-1])
    return found


def sibling_texture(mesh_file: Path) -> Optional[Path]:
    """An image beside the mesh that is evidently its texture (the only image, or one named like it)."""
    images = sorted(p for p in mesh_file.parent.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    named = [
        p
        for p in images
        if mesh_file.stem.split("_")[0].lower() in p.stem.lower()
        or any(k in p.stem.lower() for k in ("texture", "diffuse", "albedo", "basecolor"))
    ]
    return images[0] if len(images) == 1 else named[0] if len(named) == 1 else None


def load_mesh_parts(path: Path, up: Literal["y", "z"] = "y") -> List[Part]:
    """Load a user's mesh (with texture or colors) as Parts, z-up, centred and scaled into SCENE_RADIUS."""
    # deferred: the scene generator's 3D stack
    import trimesh

    mesh_file = resolve_mesh_file(path)
    textures = obj_texture_files(mesh_file) if mesh_file.suffix.lower() == ".obj" else []
    for tex in textures:
        if not tex.is_file():
            raise SceneError(
                f"texture {tex} named by {mesh_file} does not exist; put it next to the .mtl or delete the map_Kd line"
            )
        read_texture(tex)
    fallback = textures[0] if textures else sibling_texture(mesh_file)
    try:
        loaded = trimesh.load(str(mesh_file))
        meshes = loaded.dump(concatenate=False) if isinstance(loaded, trimesh.Scene) else [loaded]
    except Exception as exc:  # trimesh raises many kinds of errors on malformed files
        detail = (str(exc).strip().splitlines() or [""])[0]
        raise SceneError(
            f"cannot read mesh {mesh_file} ({type(exc).__name__}: {detail}); "
            "pass --mesh with a valid .obj/.ply/.glb or omit it for the built-in scene"
        ) from None
    meshes = [m for m in meshes if isinstance(m, trimesh.Trimesh) and len(m.faces)]
    if not meshes:
        raise SceneError(
            f"mesh {mesh_file} has no triangles; pass --mesh with a valid .obj/.ply/.glb "
            "or omit it for the built-in scene"
        )
    points = np.concatenate([m.vertices for m in meshes])
    if not np.isfinite(points).all() or np.ptp(points, axis=0).max() <= 0:
        raise SceneError(f"mesh {mesh_file} has degenerate or non-finite vertices; pass --mesh with a valid mesh")
    to_z_up = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64) if up == "y" else np.eye(3)
    center = (points.min(axis=0) + points.max(axis=0)) / 2
    scale = SCENE_RADIUS / np.linalg.norm(points - center, axis=1).max()
    parts = []
    for m in meshes:
        verts = (np.asarray(m.vertices) - center) @ to_z_up.T * scale
        normals = np.asarray(m.vertex_normals) @ to_z_up.T
        visual, part = m.visual, dict(vertices=verts, faces=np.asarray(m.faces), normals=normals)
        uv = getattr(visual, "uv", None)
        if getattr(visual, "kind", None) == "texture" and uv is not None and len(uv) == len(verts):
            material = getattr(visual, "material", None)
            image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
            if mesh_file.suffix.lower() == ".obj" and not textures:
                image = None  # an .obj without map_Kd gets a placeholder image from trimesh
            texture = (
                np.asarray(image.convert("RGB"))
                if image is not None
                else (read_texture(fallback) if fallback is not None else None)
            )
            if texture is not None:
                parts.append(Part(**part, uv=np.asarray(uv, dtype=np.float64), texture=texture))
                continue
        if getattr(visual, "kind", None) in ("vertex", "face"):
            parts.append(Part(**part, vertex_colors=np.asarray(visual.vertex_colors)[:, :3].astype(np.uint8)))
            continue
        material = getattr(visual, "material", None)
        rgba = getattr(material, "diffuse", None)
        rgba = getattr(material, "baseColorFactor", None) if rgba is None else rgba
        color = tuple(float(c) / 255 for c in np.asarray(rgba)[:3]) if rgba is not None else (0.8, 0.8, 0.8)
        parts.append(Part(**part, color=color))  # type: ignore[arg-type]
    return parts


# ----------------------------------------------------------------------------- rendering


def make_plotter(parts: Sequence[Part], size: int):
    """An off-screen pyvista Plotter (no multisampling, transparent black background) holding ``parts``."""
    # deferred: the scene generator's 3D stack
    import pyvista as pv
    from vtkmodules.vtkCommonCore import vtkLogger

    # Headless, VTK first tries X ("bad X server connection") and then falls back to EGL/OSMesa on its own.
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=(size, size), lighting="light_kit")
    plotter.render_window.SetMultiSamples(0)  # coverage comes from our own supersampling, not MSAA
    plotter.set_background("black")
    for part in parts:
        poly = pv.PolyData(part.vertices, np.hstack([np.full((len(part.faces), 1), 3), part.faces]).ravel())
        if part.normals is not None:
            poly.point_data["Normals"] = part.normals
            poly.point_data.active_normals_name = "Normals"
        kwargs: dict = dict(specular=0.2, ambient=0.15, diffuse=0.85)
        if part.texture is not None and part.uv is not None:
            poly.active_texture_coordinates = part.uv
            texture = pv.Texture(part.texture)
            texture.repeat, texture.interpolate = True, True
            kwargs["texture"] = texture
        elif part.vertex_colors is not None:
            poly.point_data["RGB"] = part.vertex_colors
            kwargs.update(scalars="RGB", rgb=True)
        else:
            kwargs["color"] = part.color
        plotter.add_mesh(poly, show_scalar_bar=False, **kwargs)
    return plotter


def render_view(
    plotter, c2w: Float[np.ndarray, "4 4"], resolution: int, supersample: int, camera_angle_x: float = CAMERA_ANGLE_X
) -> Tuple[UInt8[np.ndarray, "h w 4"], Float[np.ndarray, "h w"]]:
    """Render one view; returns straight-alpha RGBA (alpha = coverage) and z-depth (0 where empty)."""
    camera = plotter.camera
    camera.position = tuple(c2w[:3, 3])
    camera.focal_point = tuple(c2w[:3, 3] - c2w[:3, 2])
    camera.up = tuple(c2w[:3, 1])
    camera.view_angle = math.degrees(camera_angle_x)  # square images: vertical = horizontal field of view
    camera.clipping_range = (0.5, 10.0)
    plotter.render()
    rgba = plotter.screenshot(transparent_background=True, return_img=True).astype(np.float64) / 255.0
    z = -plotter.get_image_depth(fill_value=np.nan, reset_camera_clipping_range=False)
    s, n = supersample, resolution
    alpha = rgba[..., 3].reshape(n, s, n, s)
    weight = alpha.sum(axis=(1, 3))
    rgb = (rgba[..., :3] * rgba[..., 3:]).reshape(n, s, n, s, 3).sum(axis=(1, 3)) / np.maximum(weight, 1e-12)[..., None]
    hit = np.isfinite(z).reshape(n, s, n, s)
    zsum = np.where(hit, z.reshape(n, s, n, s), 0.0).sum(axis=(1, 3))
    hits = hit.sum(axis=(1, 3))
    depth = np.where(hits > 0, zsum / np.maximum(hits, 1), 0.0)
    out = np.concatenate([rgb, (weight / (s * s))[..., None]], axis=-1)
    out = np.round(np.clip(out, 0.0, 1.0) * 255).astype(np.uint8)
    depth = np.where(out[..., 3] > 0, depth, 0.0)
    return out, depth.astype(np.float32)


def write_png(path: Path, rgba: UInt8[np.ndarray, "h w 4"]) -> None:
    """Write straight (unassociated) alpha RGBA as an 8-bit PNG with OpenImageIO."""
    # deferred: native image library, only image I/O needs it
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(rgba.shape[1], rgba.shape[0], 4, oiio.UINT8)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    _write_image(path, spec, rgba)


def write_rgb_png(path: Path, rgb: UInt8[np.ndarray, "h w 3"]) -> None:
    """Write an opaque 8-bit RGB PNG with OpenImageIO."""
    # deferred: native image library, only image I/O needs it
    import OpenImageIO as oiio

    _write_image(path, oiio.ImageSpec(rgb.shape[1], rgb.shape[0], 3, oiio.UINT8), rgb)


def write_depth_exr(path: Path, depth: Float[np.ndarray, "h w"]) -> None:
    """Write z-depth (world units along the optical axis, 0 = background) as a one-channel float32 EXR."""
    # deferred: native image library, only image I/O needs it
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(depth.shape[1], depth.shape[0], 1, oiio.FLOAT)
    spec.channelnames = ("Z",)
    spec.attribute("compression", "zip")
    spec.attribute("DateTime", "2000:01:01 00:00:00")  # fixed, else OpenEXR files differ run to run
    _write_image(path, spec, depth[..., None])


def _write_image(path: Path, spec, pixels: np.ndarray) -> None:
    # deferred: native image library, only image I/O needs it
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec) or not out.write_image(np.ascontiguousarray(pixels)):
        reason = (out.geterror() if out is not None else oiio.geterror()) or "unknown error"
        raise OSError(f"cannot write {path}: {reason}")
    out.close()


def write_dataset(parts: Sequence[Part], folder: Path, config: SceneConfig, progress: bool = True) -> None:
    """Render every split into ``folder`` (which must exist): PNGs, depth EXRs and transforms_*.json (``--layout
    capture``: :func:`write_capture`)."""
    if config.layout == "capture":
        write_capture([*parts, *capture_backdrop()], folder, config, progress)
        return
    counts = {"train": config.num_train, "val": config.num_val, "test": config.num_test}
    poses = split_poses(config.seed, counts)
    plotter = make_plotter(parts, config.resolution * config.supersample)
    try:
        with tqdm(
            total=sum(counts.values()), desc="rendering views", unit="view", disable=None if progress else True
        ) as bar:
            for split in SPLITS:
                (folder / split).mkdir()
                frames = []
                for i, c2w in enumerate(poses[split]):
                    rgba, depth = render_view(plotter, c2w, config.resolution, config.supersample)
                    write_png(folder / split / f"r_{i}.png", rgba)
                    write_depth_exr(folder / split / f"r_{i}_depth.exr", depth)
                    frames.append(
                        {
                            "file_path": f"./{split}/r_{i}",
                            "rotation": 2 * math.pi / len(poses[split]),
                            "transform_matrix": c2w.tolist(),
                            "depth_file_path": f"./{split}/r_{i}_depth.exr",
                        }
                    )
                    bar.update(1)
                meta = {
                    "camera_angle_x": CAMERA_ANGLE_X,
                    "near": NEAR,
                    "far": FAR,
                    "depth": "z-depth in world units along the camera's viewing axis; 0 where empty",
                    "scene": str(config.mesh) if config.mesh else "builtin",
                    "seed": config.seed,
                    "frames": frames,
                }
                (folder / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2) + "\n")
    finally:
        plotter.close()


def write_capture(parts: Sequence[Part], folder: Path, config: SceneConfig, progress: bool = True) -> None:
    """The forward-facing capture in the nerfstudio-data layout: ``images/<split>_NNN.png`` (RGB) and one
    ``transforms.json`` (intrinsics ``fl_x, fl_y, cx, cy, w, h``, OpenGL camera-to-world frames, split file lists)."""
    counts = {"train": config.num_train, "val": config.num_val, "test": config.num_test}
    poses = split_poses(config.seed, counts, "capture")
    n = config.resolution
    focal = 0.5 * n / math.tan(0.5 * CAMERA_ANGLE_X)
    (folder / "images").mkdir()
    frames: List[Dict] = []
    names: Dict[str, List[str]] = {s: [] for s in SPLITS}
    plotter = make_plotter(parts, n * config.supersample)
    try:
        with tqdm(
            total=sum(counts.values()), desc="rendering views", unit="view", disable=None if progress else True
        ) as bar:
            for split in SPLITS:
                for i, c2w in enumerate(poses[split]):
                    rgba, _ = render_view(plotter, c2w, n, config.supersample)
                    if int(rgba[..., 3].min()) < 255:
                        raise SceneError(
                            f"view {split} {i} sees past the capture's wall and floor; use the built-in scene or a "
                            "mesh within 1.2 units of the origin"
                        )
                    name = f"images/{split}_{i:03d}.png"
                    write_rgb_png(folder / name, rgba[..., :3])
                    frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
                    names[split].append(name)
                    bar.update(1)
    finally:
        plotter.close()
    meta = {
        "camera_model": "OPENCV",
        "fl_x": focal,
        "fl_y": focal,
        "cx": n / 2.0,
        "cy": n / 2.0,
        "w": n,
        "h": n,
        "scene": (str(config.mesh) if config.mesh else "builtin") + " (forward-facing capture)",
        "seed": config.seed,
        "frames": frames,
        **{f"{s}_filenames": names[s] for s in SPLITS},
    }
    (folder / "transforms.json").write_text(json.dumps(meta, indent=2) + "\n")


# ----------------------------------------------------------------------------- command line


def validate(config: SceneConfig) -> None:
    """Check the numeric flags, raising SceneError with a fix."""
    for flag, value, low in [
        ("--resolution", config.resolution, 8),
        ("--num-train", config.num_train, 1),
        ("--num-val", config.num_val, 1),
        ("--num-test", config.num_test, 1),
        ("--supersample", config.supersample, 1),
    ]:
        if value < low:
            raise SceneError(f"{flag} is {value} but must be at least {low}; pass {flag} {max(low, 1)} or more")


def _prepare_output(output: Path, overwrite: bool) -> Tuple[Path, Optional[Path]]:
    """Check --output-dir; create the temporary sibling folder to render into (and the parents it needs).

    Returns the temporary folder and the outermost parent folder this created (None if none), so a
    failed run can remove them again.
    """
    if output.exists() or output.is_symlink():
        if not overwrite:
            raise SceneError(
                f"output folder {output} already exists; pass --overwrite to replace it or choose another --output-dir"
            )
        ours = (output / "transforms_train.json").exists() or (output / "transforms.json").exists()
        if not output.is_dir() or (any(output.iterdir()) and not ours):
            raise SceneError(
                f"output path {output} exists and is not a dataset written by this command (no "
                "transforms_train.json or transforms.json), so --overwrite will not delete it; choose another --output-dir"
            )
    missing = [p for p in output.parents if not p.exists()]
    blocker = next((p for p in output.parents if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise SceneError(
            f"cannot write to output folder {output} because {blocker} is a file, not a folder; "
            "pass --output-dir with a writable location"
        )
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{output.name}.partial-", dir=output.parent))
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)  # mkdtemp makes it private; the dataset should get the usual permissions
        return tmp, (missing[-1] if missing else None)
    except OSError as exc:
        if missing:
            shutil.rmtree(missing[-1], ignore_errors=True)
        raise SceneError(
            f"cannot write to output folder {output} ({exc.strerror or exc}); "
            "pass --output-dir with a writable location"
        ) from None


def _commit(tmp: Path, output: Path) -> None:
    """Move the finished dataset into place, replacing an old one only after the new one is complete."""
    old = None
    if output.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{output.name}.old-", dir=output.parent))
        os.replace(output, old / "data")
    os.replace(tmp, output)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _raise_interrupt(signum, frame):  # noqa: ARG001
    raise KeyboardInterrupt


def main(config: SceneConfig, progress: bool = True) -> int:
    """Run the command; returns the exit status (0 ok, 2 bad input or unwritable output, 130 interrupted)."""
    tmp: Optional[Path] = None
    created: Optional[Path] = None
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_interrupt) if in_main_thread else None
    output = config.output_dir.expanduser().absolute()
    try:
        validate(config)
        tmp, created = _prepare_output(output, config.overwrite)
        parts = load_mesh_parts(config.mesh.expanduser(), config.mesh_up) if config.mesh else builtin_scene()
        write_dataset(parts, tmp, config, progress=progress)
        _commit(tmp, output)
        tmp = created = None
    except SceneError as exc:
        return print_error(str(exc))
    except OSError as exc:
        return print_error(f"writing the dataset failed ({exc}); check free space and permissions of {output.parent}")
    except KeyboardInterrupt:
        print_error("interrupted; no dataset was written (rerun the command to render it)")
        return 130
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous)
        for leftover in (tmp, created):
            if leftover is not None:
                shutil.rmtree(leftover, ignore_errors=True)
    n = config.num_train + config.num_val + config.num_test
    print(f"wrote {n} views ({config.resolution}x{config.resolution}) to {output}")
    return 0


def entrypoint() -> None:
    """Console script ``ns-gsticker-scene``."""
    config = tyro.cli(SceneConfig)
    sys.exit(run_command(lambda: main(config)))


if __name__ == "__main__":
    entrypoint()
