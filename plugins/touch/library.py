"""The project's shape library: 10 known classes and 10 novel variants of them.

Each shape is a signed-distance field built from primitives (revolved profiles, boxes,
tori, spheres, capsules; union = min, smoothed where parts meet), sampled on a grid and turned
into a watertight mesh by marching cubes, then scaled so that its largest extent is 0.2 m.
Shapes are rebuilt from this code on first use (about 0.1 s each) and kept in memory; nothing
generated is stored on disk. Any mesh file becomes a class with :func:`load_class`, read as
saved (metres, its own object frame; not rescaled or re-centred), like the learned shapes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import cache
from pathlib import Path

import numpy as np
from vistac.errors import DataError, suggest
from vistac.plugins.touch.meshes import (
    DEFAULT_SIZE_M,
    MESH_SUFFIXES,
    Mesh,
    load_mesh,
    make_mesh,
)
from vistac.types import FloatArray

log = logging.getLogger(__name__)

Field = Callable[[FloatArray], FloatArray]
"""points [N, 3] (design units) -> signed distance [N] (negative inside)."""

GRID_CELLS = 56
"""Grid cells along the largest extent for marching cubes."""


# --- primitives (p: [N, 3]) -------------------------------------------------------------


def _polygon_2d(q: FloatArray, polygon: FloatArray) -> FloatArray:
    """Signed distance of 2D points q [N, 2] to a closed polygon [E, 2] (negative inside)."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    edge = b - a  # [E, 2]
    rel = q[:, None, :] - a[None]  # [N, E, 2]
    t = np.clip((rel * edge).sum(-1) / np.maximum((edge * edge).sum(-1), 1e-12), 0.0, 1.0)
    dist = np.linalg.norm(rel - t[..., None] * edge, axis=-1).min(axis=1)
    crosses = (a[None, :, 1] <= q[:, None, 1]) != (b[None, :, 1] <= q[:, None, 1])
    x_at = a[None, :, 0] + (q[:, None, 1] - a[None, :, 1]) * edge[None, :, 0] / np.where(
        edge[None, :, 1] == 0.0, 1.0, edge[None, :, 1]
    )
    inside = (crosses & (q[:, None, 0] < x_at)).sum(axis=1) % 2 == 1
    return np.where(inside, -dist, dist)


def revolved(profile: list[tuple[float, float]]) -> Field:
    """A solid of revolution about z from a (radius, z) outline that starts and ends on the
    axis (radius 0)."""
    polygon = np.array(profile, dtype=np.float64)
    off_axis = polygon[polygon[:, 0] > 0.0]
    mirrored = np.concatenate([polygon, (off_axis * [-1.0, 1.0])[::-1]])

    def field(p: FloatArray) -> FloatArray:
        q = np.stack([np.linalg.norm(p[:, :2], axis=1), p[:, 2]], axis=1)
        return _polygon_2d(q, mirrored)

    return field


def box(
    centre: tuple[float, float, float], half: tuple[float, float, float], rounding: float = 0.0
) -> Field:
    """An axis-aligned box with rounded edges (``rounding`` inside the half extents)."""
    c, h = np.array(centre), np.array(half) - rounding

    def field(p: FloatArray) -> FloatArray:
        q = np.abs(p - c) - h
        return (
            np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0) - rounding
        )

    return field


def sphere(centre: tuple[float, float, float], radius: float) -> Field:
    c = np.array(centre)
    return lambda p: np.linalg.norm(p - c, axis=1) - radius


def capsule(a: tuple[float, float, float], b: tuple[float, float, float], radius: float) -> Field:
    """All points within ``radius`` of the segment a-b."""
    start, seg = np.array(a), np.array(b) - np.array(a)

    def field(p: FloatArray) -> FloatArray:
        t = np.clip((p - start) @ seg / (seg @ seg), 0.0, 1.0)
        return np.linalg.norm(p - start - t[:, None] * seg, axis=1) - radius

    return field


def torus_xz(centre: tuple[float, float, float], major: float, minor: float) -> Field:
    """A torus in the x-z plane (its axis along y): a mug handle."""
    c = np.array(centre)

    def field(p: FloatArray) -> FloatArray:
        q = p - c
        ring = np.linalg.norm(q[:, [0, 2]], axis=1) - major
        return np.sqrt(ring**2 + q[:, 1] ** 2) - minor

    return field


def cylinder_y(centre: tuple[float, float, float], radius: float, half_y: float) -> Field:
    """A cylinder with its axis along y."""
    c = np.array(centre)

    def field(p: FloatArray) -> FloatArray:
        q = p - c
        d = np.stack([np.linalg.norm(q[:, [0, 2]], axis=1) - radius, np.abs(q[:, 1]) - half_y], 1)
        return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0)

    return field


def union(*parts: Field, smooth: float = 0.0) -> Field:
    """CSG union (min); with ``smooth`` > 0 a polynomial smooth minimum blends the parts."""

    def field(p: FloatArray) -> FloatArray:
        values = [part(p) for part in parts]
        result = values[0]
        for value in values[1:]:
            if smooth <= 0.0:
                result = np.minimum(result, value)
            else:
                h = np.clip(0.5 + 0.5 * (value - result) / smooth, 0.0, 1.0)
                result = value * (1 - h) + result * h - smooth * h * (1 - h)
        return result

    return field


# --- the classes (design units, z up) -----------------------------------------------------


def mug(height: float = 1.0) -> Field:
    body = revolved([(0.0, 0.0), (0.4, 0.0), (0.4, height), (0.0, height)])
    handle = torus_xz((0.42, 0.0, height / 2), 0.24 * height**0.5, 0.06)
    return union(body, handle, smooth=0.03)


def bottle(body_radius: float = 0.3, neck_top: float = 1.25) -> Field:
    return revolved(
        [
            (0.0, 0.0),
            (body_radius, 0.0),
            (body_radius, 0.7),
            (0.1, 0.95),
            (0.1, neck_top - 0.06),
            (0.13, neck_top - 0.05),
            (0.13, neck_top),
            (0.0, neck_top),
        ]
    )


def vase(waist: float = 0.17, belly: float = 0.45, height: float = 1.2) -> Field:
    return revolved(
        [
            (0.0, 0.0),
            (0.22, 0.0),
            (belly, 0.35 * height),
            (belly * 0.9, 0.5 * height),
            (waist, 0.78 * height),
            (0.3, height),
            (0.0, height),
        ]
    )


def cone(top_radius: float = 0.0) -> Field:
    outline = [(0.0, 0.0), (0.5, 0.0), (top_radius, 1.0), (0.0, 1.0)]
    return revolved(outline if top_radius > 0 else [(0.0, 0.0), (0.5, 0.0), (0.0, 1.0)])


def ice_cream(scoops: int = 1) -> Field:
    wafer = revolved([(0.0, 0.0), (0.28, 0.75), (0.0, 0.75)])
    balls = [sphere((0.0, 0.0, 0.8 + 0.42 * i), 0.3 - 0.04 * i) for i in range(scoops)]
    return union(wafer, *balls, smooth=0.04)


def chair(back_height: float = 0.55, arms: bool = False) -> Field:
    legs = [box((x, y, 0.22), (0.035, 0.035, 0.22)) for x in (-0.22, 0.22) for y in (-0.22, 0.22)]
    seat = box((0.0, 0.0, 0.47), (0.27, 0.27, 0.04), 0.01)
    back = box((0.0, 0.235, 0.47 + back_height / 2), (0.27, 0.035, back_height / 2), 0.01)
    extra = (
        [box((s * 0.25, 0.0, 0.65), (0.025, 0.25, 0.025), 0.01) for s in (-1, 1)] if arms else []
    )
    return union(*legs, seat, back, *extra)


def sofa(length: float = 1.0, arms: bool = True) -> Field:
    base = box((0.0, 0.0, 0.15), (length / 2, 0.25, 0.15), 0.03)
    back = box((0.0, 0.2, 0.4), (length / 2, 0.07, 0.3), 0.03)
    sides = [box((s * (length / 2 - 0.06), 0.0, 0.3), (0.06, 0.27, 0.2), 0.03) for s in (-1, 1)]
    return union(base, back, *(sides if arms else []))


def guitar(neck_length: float = 0.5) -> Field:
    lower = cylinder_y((0.0, 0.0, 0.0), 0.3, 0.08)
    upper = cylinder_y((0.0, 0.0, 0.42), 0.22, 0.08)
    neck = box((0.0, 0.0, 0.6 + neck_length / 2), (0.05, 0.03, neck_length / 2 + 0.05))
    head = box((0.0, 0.0, 0.68 + neck_length), (0.08, 0.035, 0.1), 0.02)
    return union(union(lower, upper, smooth=0.12), neck, head, smooth=0.02)


def hammer(head_length: float = 0.55, claw: bool = False) -> Field:
    handle = box((0.0, 0.0, 0.45), (0.05, 0.035, 0.45), 0.02)
    head = box((0.0, 0.0, 0.95), (head_length / 2, 0.07, 0.07), 0.02)
    parts = [handle, head]
    if claw:
        parts.append(
            capsule((-head_length / 2, 0.0, 0.95), (-head_length / 2 - 0.15, 0.0, 0.8), 0.05)
        )
    return union(*parts)


def dumbbell(bar_length: float = 0.6, cubes: bool = False) -> Field:
    half = bar_length / 2
    weight = (
        (lambda x: box((x, 0.0, 0.0), (0.14, 0.2, 0.2), 0.03))
        if cubes
        else (lambda x: sphere((x, 0.0, 0.0), 0.22))
    )
    return union(
        capsule((-half, 0.0, 0.0), (half, 0.0, 0.0), 0.06), weight(-half), weight(half), smooth=0.03
    )


KNOWN: dict[str, Callable[[], Field]] = {
    "mug": mug,
    "bottle": bottle,
    "vase": vase,
    "cone": cone,
    "ice_cream": ice_cream,
    "chair": chair,
    "sofa": sofa,
    "guitar": guitar,
    "hammer": hammer,
    "dumbbell": dumbbell,
}

NOVEL: dict[str, tuple[str, Callable[[], Field]]] = {
    "mug_tall": ("mug", lambda: mug(height=1.6)),
    "bottle_wide": ("bottle", lambda: bottle(body_radius=0.45, neck_top=1.05)),
    "vase_squat": ("vase", lambda: vase(waist=0.28, belly=0.55, height=0.8)),
    "cone_truncated": ("cone", lambda: cone(top_radius=0.22)),
    "ice_cream_double": ("ice_cream", lambda: ice_cream(scoops=2)),
    "chair_armchair": ("chair", lambda: chair(back_height=0.45, arms=True)),
    "sofa_armless": ("sofa", lambda: sofa(length=1.3, arms=False)),
    "guitar_long_neck": ("guitar", lambda: guitar(neck_length=0.95)),
    "hammer_claw": ("hammer", lambda: hammer(head_length=0.4, claw=True)),
    "dumbbell_cubes": ("dumbbell", lambda: dumbbell(bar_length=0.5, cubes=True)),
}
"""Novel variant -> (the known class it derives from, its field)."""


def _bounds(field: Field) -> tuple[FloatArray, FloatArray]:
    """Bounding box of a field's interior from a coarse grid over [-1.5, 2]^3 (design units)."""
    axis = np.linspace(-1.5, 2.0, 36)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    inside = grid[field(grid) < 0.0]
    if len(inside) == 0:
        raise DataError("a library shape has no interior")
    return inside.min(axis=0) - 0.25, inside.max(axis=0) + 0.25


def mesh_from_field(
    name: str, field: Field, cells: int = GRID_CELLS, size_m: float = DEFAULT_SIZE_M
) -> Mesh:
    """Marching cubes of ``field``'s zero level on a grid with ``cells`` along its largest
    extent, scaled to ``size_m``; the result is watertight (the field is positive on the grid
    boundary)."""
    from skimage.measure import marching_cubes

    low, high = _bounds(field)
    step = float((high - low).max()) / cells
    counts = np.ceil((high - low) / step).astype(int) + 1
    axes = [low[i] + step * np.arange(counts[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    values = field(grid).reshape(*counts)
    values[values == 0.0] = 1e-9  # exact zeros at grid points make non-manifold vertices
    vertices, faces, _, _ = marching_cubes(
        values, 0.0, spacing=(step, step, step), allow_degenerate=False
    )
    return make_mesh(name, vertices + low, faces, f"library:{name}", size_m)


@cache
def known_class(name: str) -> Mesh:
    """One known class by name (built once per process)."""
    if name not in KNOWN:
        raise DataError(f"unknown shape class {name!r}; known: {', '.join(KNOWN)}")
    return mesh_from_field(name, KNOWN[name]())


@cache
def novel_class(name: str) -> Mesh:
    """One novel variant by name (built once per process)."""
    if name not in NOVEL:
        raise DataError(f"unknown novel shape {name!r}; novel: {', '.join(NOVEL)}")
    return mesh_from_field(name, NOVEL[name][1]())


def known_classes() -> dict[str, Mesh]:
    """The 10 known classes: name -> mesh (largest extent 0.2 m, centred)."""
    return {name: known_class(name) for name in KNOWN}


def novel_classes() -> dict[str, Mesh]:
    """The 10 novel variants: name -> mesh (each derived from known class ``NOVEL[name][0]``)."""
    return {name: novel_class(name) for name in NOVEL}


MESH_FILE_EXTENT_M = (0.01, 1.0)
"""Largest extents (m) outside this range are logged as a likely unit mistake."""


def load_class(path: Path | str) -> tuple[str, Mesh]:
    """Any mesh file as a class: (its name = the file stem, the mesh as saved: metres, in
    the file's own object frame, not normalised -- a learned shape keeps its size and frame)."""
    path = Path(path)
    mesh = load_mesh(path, size_m=None)
    low, high = MESH_FILE_EXTENT_M
    if not low <= float(mesh.extent_m.max()) <= high:
        log.warning("%s is %.3g m across; mesh files are read in metres as saved (is it in "
                    "mm or cm?)", path, float(mesh.extent_m.max()))  # fmt: skip
    return mesh.name, mesh


def shape_name(spec: str) -> str:
    """The class name ``spec`` resolves to: a library name as is, a mesh file's stem."""
    return spec if spec in KNOWN or spec in NOVEL else Path(spec).stem


def missing_shape(spec: str, base: Path | None = None) -> str | None:
    """Why ``spec`` names no shape that :func:`resolve_shape` can give (a library name, or a
    mesh file that exists; a relative path from ``base``), or None when it names one."""
    path = Path(base or "") / spec  # an absolute spec stays as it is
    if spec in KNOWN or spec in NOVEL or (path.suffix.lower() in MESH_SUFFIXES and path.is_file()):
        return None
    return (
        f"{spec!r} is no library shape ({', '.join([*KNOWN, *NOVEL])}) and no mesh file "
        f"({', '.join(MESH_SUFFIXES)}) there is{suggest(spec, [*KNOWN, *NOVEL])}"
    )


def require_shape_in_skill(spec: str, skill_dir: Path | None) -> str:
    """``spec`` as it is when it names a shape, a relative path taken from the skill's folder;
    a ValueError (a config check's) saying why not otherwise. Without a skill's folder nothing
    is checked: the component's build will."""
    problem = missing_shape(spec, skill_dir) if skill_dir is not None else None
    if problem:
        raise ValueError(f"{problem}; a relative path is taken from the skill's folder")
    return spec


def resolve_shape(spec: str, base: Path | None = None) -> Mesh:
    """A known class or novel variant (largest extent 0.2 m, centred), or a mesh file path
    (relative to ``base``) read as saved by :func:`load_class`."""
    if spec in KNOWN:
        return known_class(spec)
    if spec in NOVEL:
        return novel_class(spec)
    path = Path(spec)
    if base is not None and not path.is_absolute():
        path = base / path
    if path.suffix:
        return load_class(path)[1]
    raise DataError(
        f"{spec!r} is neither a library shape ({', '.join([*KNOWN, *NOVEL])}) nor a mesh file"
    )
