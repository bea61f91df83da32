"""Object definitions: footprints, per-link parameters, 2-link attachment, the 120-object set.

Pure data and geometry (no MuJoCo): simulated worlds build their models from an
:class:`ObjectSpec`, evaluation code compares estimates with it.

Frames. Every footprint polygon is given in its link frame: origin at the footprint's area
centroid on the table surface (z = 0), x and y in the table plane. ``ObjectSpec.pose`` places
link 0's frame in the world. Link ``k > 0`` hangs off the +x side of link ``k - 1``: its frame
is shifted along x so that the footprints' extreme points (the midpoints of their outermost
edges) touch, with a ``gap`` of :data:`HINGE_GAP_M` for articulated objects so that the
leaves can turn. An articulated object's hinge (axis z) sits in the middle of that gap.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from vistac.errors import ConfigError, ConfigIssue, validation_issues
from vistac.skill import read_yaml

FloatArray = NDArray[np.float64]

ObjectType = Literal["homogeneous", "heterogeneous", "articulated"]
OBJECT_TYPES: tuple[ObjectType, ...] = ("homogeneous", "heterogeneous", "articulated")

HINGE_GAP_M = 0.004
"""Gap between the facing sides of two hinged links (welded links touch)."""

_ELLIPSE_VERTICES = 48
_BUTTER_VERTICES = 48
_BUTTER_EXPONENT = 3.0
_BUTTER_TAPER = 0.18

# Footprint sizes in mm: width along the link's x axis, length along its y axis.
_RECTANGLES_MM = {"rect1": (90.0, 90.0), "rect2": (90.0, 112.5), "rect3": (135.0, 90.0)}
_TRIANGLES_MM = {"tri1": (126.0, 126.0), "tri2": (151.2, 126.0), "tri3": (176.4, 126.0)}
_ELLIPSES_MM = {"ellip1": (104.9, 104.9), "ellip2": (104.8, 131.0), "ellip3": (104.8, 157.2)}
_HEXAGON_CIRCUMRADIUS_MM = 60.5
_BUTTER_MM = (95.5, 157.3)

FOOTPRINTS: tuple[str, ...] = (
    *_RECTANGLES_MM,
    *_TRIANGLES_MM,
    *_ELLIPSES_MM,
    "hexagon",
    "butter",
)
"""The footprint names of the pushing-benchmark shapes."""

Footprint = Literal[
    "rect1", "rect2", "rect3", "tri1", "tri2", "tri3",
    "ellip1", "ellip2", "ellip3", "hexagon", "butter",
]  # fmt: skip

MASS_RANGE_KG = (0.2, 1.6)
FRICTION_RANGE = (0.1, 0.5)
COM_SHRINK = 0.95
"""A generated link's CoM is uniform inside its footprint shrunk by this factor towards the
centroid (so that it stays clearly inside the outline)."""
HEIGHT_RANGE_M = (0.04, 0.06)
JOINT_FRICTION_RANGE_NM = (0.0, 0.5)


# ---------------------------------------------------------------------------------------------
# Footprint geometry


def _polygon_area_centroid(polygon: FloatArray) -> tuple[float, FloatArray]:
    """Signed area and area centroid [2] of a simple polygon [K, 2]."""
    x, y = polygon[:, 0], polygon[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * float(cross.sum())
    centroid = np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)
    return area, centroid


def _ellipse(width_m: float, length_m: float, count: int) -> FloatArray:
    # count is a multiple of 4 so that the vertices include the four axis extremes.
    angle = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    return np.stack([0.5 * width_m * np.cos(angle), 0.5 * length_m * np.sin(angle)], axis=1)


def _butter(width_m: float, length_m: float) -> FloatArray:
    """A superellipse whose width tapers linearly along its length, scaled to the size."""
    angle = np.linspace(0.0, 2.0 * np.pi, _BUTTER_VERTICES, endpoint=False)
    power = 2.0 / _BUTTER_EXPONENT
    x = np.sign(np.cos(angle)) * np.abs(np.cos(angle)) ** power
    y = np.sign(np.sin(angle)) * np.abs(np.sin(angle)) ** power
    x = x * (1.0 - _BUTTER_TAPER * y)
    x *= width_m / (x.max() - x.min())
    return np.stack([x, 0.5 * length_m * y], axis=1)


def _hexagon(circumradius_m: float) -> FloatArray:
    angle = np.arange(6) * np.pi / 3.0
    return circumradius_m * np.stack([np.cos(angle), np.sin(angle)], axis=1)


def _raw_footprint(name: str) -> FloatArray:
    if name in _RECTANGLES_MM:
        w, h = (v / 1000.0 for v in _RECTANGLES_MM[name])
        return np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
    if name in _TRIANGLES_MM:
        a, b = (v / 1000.0 for v in _TRIANGLES_MM[name])
        return np.array([[0.0, 0.0], [a, 0.0], [0.0, b]])
    if name in _ELLIPSES_MM:
        w, h = (v / 1000.0 for v in _ELLIPSES_MM[name])
        return _ellipse(w, h, _ELLIPSE_VERTICES)
    if name == "hexagon":
        return _hexagon(_HEXAGON_CIRCUMRADIUS_MM / 1000.0)
    if name == "butter":
        return _butter(_BUTTER_MM[0] / 1000.0, _BUTTER_MM[1] / 1000.0)
    raise KeyError(f"unknown footprint {name!r}; known: {', '.join(FOOTPRINTS)}")


def footprint_polygon(name: str) -> FloatArray:
    """Counter-clockwise convex outline of footprint ``name``, centred on its area centroid.

    Returns: [K, 2] vertices in metres (link frame).
    """
    polygon = _raw_footprint(name)
    area, centroid = _polygon_area_centroid(polygon)
    if area < 0:
        polygon = polygon[::-1]
    return polygon - centroid


def polygon_second_moments(polygon: FloatArray) -> FloatArray:
    """Area moments about the origin of a CCW polygon [K, 2]: [3] = (∫x², ∫y², ∫xy) dA."""
    x, y = polygon[:, 0], polygon[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    ixx = ((x * x + x * xn + xn * xn) * cross).sum() / 12.0
    iyy = ((y * y + y * yn + yn * yn) * cross).sum() / 12.0
    ixy = ((x * yn + 2 * x * y + 2 * xn * yn + xn * y) * cross).sum() / 24.0
    return np.array([ixx, iyy, ixy])


def polygon_area(polygon: FloatArray) -> float:
    """Area (m²) of a CCW polygon [K, 2]."""
    return _polygon_area_centroid(polygon)[0]


def polygon_centroid_covariance(polygon: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean [2] and covariance [2, 2] (m, m²) of a point drawn uniformly from a CCW polygon
    [K, 2]: its area centroid and its second area moments about that centroid over its area."""
    area, centroid = _polygon_area_centroid(polygon)
    x2, y2, xy = polygon_second_moments(polygon) / area
    about_origin = np.array([[x2, xy], [xy, y2]])
    return centroid, about_origin - np.outer(centroid, centroid)


def points_inside(polygon: FloatArray, points: FloatArray) -> NDArray[np.bool_]:
    """Which points [N, 2] lie strictly inside the convex CCW polygon [K, 2]. Returns [N]."""
    edges = np.roll(polygon, -1, axis=0) - polygon
    rel = points[:, None, :] - polygon[None, :, :]
    cross = edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]
    return np.asarray(np.all(cross > 0.0, axis=1))


def uniform_inside(polygon: FloatArray, count: int, rng: np.random.Generator) -> FloatArray:
    """``count`` points [count, 2] uniform inside the convex CCW ``polygon`` [K, 2]."""
    low, high = polygon.min(axis=0), polygon.max(axis=0)
    kept: list[FloatArray] = []
    found = 0
    while found < count:
        points = rng.uniform(low, high, (2 * count, 2))
        points = points[points_inside(polygon, points)]
        kept.append(points)
        found += len(points)
    return np.concatenate(kept)[:count]


def prism_surface_points(
    polygon: FloatArray, height_m: float, count: int, rng: np.random.Generator
) -> FloatArray:
    """Points sampled uniformly by area on the closed surface of the prism that extrudes
    ``polygon`` [K, 2] (convex, CCW) from z = 0 to ``height_m``.

    Returns: [count, 3] in the link frame (m).
    """
    edges = np.roll(polygon, -1, axis=0) - polygon
    side_areas = np.linalg.norm(edges, axis=1) * height_m
    cap_area = polygon_area(polygon)
    # Triangle fan of the convex polygon for the caps.
    fan_a, fan_b = polygon[1:-1] - polygon[0], polygon[2:] - polygon[0]
    fan_areas = 0.5 * np.abs(fan_a[:, 0] * fan_b[:, 1] - fan_a[:, 1] * fan_b[:, 0])
    areas = np.concatenate([side_areas, [cap_area, cap_area]])
    which = rng.choice(len(areas), size=count, p=areas / areas.sum())
    points = np.empty((count, 3))
    side = which < len(edges)
    t, z = rng.random(side.sum()), rng.random(side.sum()) * height_m
    points[side, :2] = polygon[which[side]] + t[:, None] * edges[which[side]]
    points[side, 2] = z
    cap = ~side
    triangle = rng.choice(len(fan_areas), size=cap.sum(), p=fan_areas / fan_areas.sum())
    u, v = rng.random(cap.sum()), rng.random(cap.sum())
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    points[cap, :2] = polygon[0] + u[:, None] * fan_a[triangle] + v[:, None] * fan_b[triangle]
    points[cap, 2] = np.where(which[cap] == len(edges), 0.0, height_m)
    return points


def prism_distance_m(points_m: FloatArray, polygon: FloatArray, height_m: float) -> FloatArray:
    """Exact unsigned distance [N] from points [N, 3] (link frame) to the surface of the prism
    that extrudes the convex CCW ``polygon`` [K, 2] from z = 0 to ``height_m``."""
    start, edge = polygon, np.roll(polygon, -1, axis=0) - polygon
    rel = points_m[:, None, :2] - start[None]
    t = np.clip((rel * edge).sum(-1) / (edge * edge).sum(-1), 0.0, 1.0)
    to_edge_m = np.linalg.norm(rel - t[..., None] * edge, axis=-1).min(axis=1)
    inside = points_inside(polygon, points_m[:, :2])
    z = points_m[:, 2]
    beyond_z_m = np.maximum(np.maximum(-z, z - height_m), 0.0)
    inner_m = np.minimum(to_edge_m, np.minimum(z, height_m - z))
    outside_m = np.hypot(np.where(inside, 0.0, to_edge_m), beyond_z_m)
    return np.asarray(np.where(inside & (beyond_z_m == 0.0), inner_m, outside_m))


def to_link_frame(points_m: FloatArray, pose: FloatArray) -> FloatArray:
    """World points [N, 3] -> link frame, for a planar link pose [3] = (x, y, theta)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    dx, dy = points_m[:, 0] - pose[0], points_m[:, 1] - pose[1]
    local = points_m.copy()
    local[:, 0], local[:, 1] = c * dx + s * dy, -s * dx + c * dy
    return local


def to_world_xy(points: FloatArray, pose: FloatArray) -> FloatArray:
    """Points [N, 3] in a link frame -> world frame, for a planar pose [3] = (x, y, theta)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    world = points.copy()
    world[:, 0] = pose[0] + c * points[:, 0] - s * points[:, 1]
    world[:, 1] = pose[1] + s * points[:, 0] + c * points[:, 1]
    return world


def match_links(belief_xy: FloatArray, true_xy: FloatArray) -> dict[int, int]:
    """Belief link -> true link, minimising the summed distance of positions [Lb, 2], [Lt, 2].

    With fewer true than belief links, the surplus belief links (the farthest) stay
    unmatched; with fewer belief links, the surplus true links.
    """
    from scipy.optimize import linear_sum_assignment

    belief, true = np.asarray(belief_xy, dtype=float), np.asarray(true_xy, dtype=float)
    if len(belief) == 0 or len(true) == 0:
        return {}
    distance = np.linalg.norm(belief[:, None, :2] - true[None, :, :2], axis=-1)
    rows, columns = linear_sum_assignment(distance)  # either side may have the surplus
    return {int(b): int(t) for b, t in zip(rows, columns, strict=True)}


def com_in_frames(
    parameters: dict[str, float],
    links: dict[int, int],
    frames: FloatArray,
    link_poses: FloatArray,
) -> dict[str, float]:
    """True parameters (``com_x_t``, ``com_y_t`` in link t's frame) with each matched link's
    CoM moved into another frame: ``links`` maps frame b -> true link t, ``frames`` [B, 3] and
    ``link_poses`` [Lt, 3] are planar poses (x m, y m, theta rad) at the same instant (a
    filter's fitted frames, whose origin and yaw differ from the link frames'). The CoM of an
    unmatched link is dropped; the other entries are kept."""
    moved = {name: value for name, value in parameters.items() if not name.startswith("com_")}
    for b, t in links.items():
        com = np.array([[parameters[f"com_x_{t}"], parameters[f"com_y_{t}"], 0.0]])
        local = to_link_frame(to_world_xy(com, np.asarray(link_poses[t])), np.asarray(frames[b]))
        moved[f"com_x_{t}"], moved[f"com_y_{t}"] = float(local[0, 0]), float(local[0, 1])
    return moved


# ---------------------------------------------------------------------------------------------
# Specs


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LinkSpec(_Model):
    """One rigid link: an extruded footprint with its mass, CoM and table friction."""

    footprint: Footprint
    height_m: float = Field(ge=HEIGHT_RANGE_M[0], le=HEIGHT_RANGE_M[1])
    mass_kg: float = Field(ge=MASS_RANGE_KG[0], le=MASS_RANGE_KG[1])
    friction: float = Field(ge=FRICTION_RANGE[0], le=FRICTION_RANGE[1])
    com_m: tuple[float, float] = (0.0, 0.0)
    """CoM offset from the footprint centroid in the link frame; must lie inside the footprint."""

    @model_validator(mode="after")
    def _com_inside(self) -> LinkSpec:
        polygon = footprint_polygon(self.footprint)
        if not points_inside(polygon, np.array([self.com_m]))[0]:
            raise ValueError(
                f"com_m {list(self.com_m)} lies outside footprint {self.footprint!r} "
                f"(x in [{polygon[:, 0].min():.4f}, {polygon[:, 0].max():.4f}], "
                f"y in [{polygon[:, 1].min():.4f}, {polygon[:, 1].max():.4f}] m)"
            )
        return self

    def polygon(self) -> FloatArray:
        """Footprint outline [K, 2] in the link frame."""
        return footprint_polygon(self.footprint)


class JointSpec(_Model):
    """The hinge between two links of an articulated object."""

    friction_nm: float = Field(ge=JOINT_FRICTION_RANGE_NM[0], le=JOINT_FRICTION_RANGE_NM[1])
    damping_nms: float = Field(default=0.002, ge=0.0)


class ObjectSpec(_Model):
    """A planar object on the table: one link, or two links welded or hinged."""

    name: str = Field(min_length=1)
    type: ObjectType
    links: list[LinkSpec] = Field(min_length=1, max_length=2)
    pose: tuple[float, float, float]
    """(x_m, y_m, theta_rad) of link 0's frame in the world."""
    joint: JointSpec | None = None
    table_tilt_rad: float = Field(default=0.0, ge=-0.5, le=0.5)

    @field_validator("pose")
    @classmethod
    def _finite_pose(cls, pose: tuple[float, float, float]) -> tuple[float, float, float]:
        if not np.all(np.isfinite(pose)):
            raise ValueError("pose must be finite")
        return pose

    @model_validator(mode="after")
    def _structure(self) -> ObjectSpec:
        want_links = 1 if self.type == "homogeneous" else 2
        if len(self.links) != want_links:
            raise ValueError(
                f"a {self.type} object has {want_links} link(s), got {len(self.links)}"
            )
        if (self.type == "articulated") != (self.joint is not None):
            raise ValueError("articulated objects (and only they) need a 'joint'")
        return self

    def parameters(self) -> dict[str, float]:
        """The time-invariant parameters under the belief's entry names: ``m_i`` (kg), ``f_i``
        (table friction), ``com_x_i``/``com_y_i`` (m, link frame) per link, ``f_j_0`` (N m)."""
        values: dict[str, float] = {}
        for i, link in enumerate(self.links):
            values.update(
                {
                    f"m_{i}": link.mass_kg,
                    f"f_{i}": link.friction,
                    f"com_x_{i}": link.com_m[0],
                    f"com_y_{i}": link.com_m[1],
                }
            )
        if self.joint is not None:
            values["f_j_0"] = self.joint.friction_nm
        return values


def _side_contact(polygon: FloatArray, sign: float) -> FloatArray:
    """Midpoint [2] of the vertices at the polygon's extreme x on side ``sign`` (+1 or -1)."""
    extreme = sign * polygon[:, 0]
    on_side = polygon[extreme >= extreme.max() - 1e-9]
    return np.asarray(on_side.mean(axis=0))


def attachment(spec: ObjectSpec) -> tuple[FloatArray, FloatArray | None]:
    """Where link 1 sits in link 0's frame.

    Returns (link1_offset [2] = position of link 1's frame in link 0's frame (no relative
    rotation), hinge [2] = hinge point in link 0's frame or None when not articulated).
    """
    if len(spec.links) < 2:
        return np.zeros(2), None
    gap_m = HINGE_GAP_M if spec.type == "articulated" else 0.0
    parent_side = _side_contact(spec.links[0].polygon(), +1.0)
    child_side = _side_contact(spec.links[1].polygon(), -1.0)
    offset = parent_side - child_side + np.array([gap_m, 0.0])
    hinge = parent_side + np.array([0.5 * gap_m, 0.0]) if spec.type == "articulated" else None
    return offset, hinge


def link_frames(spec: ObjectSpec) -> FloatArray:
    """Initial world poses of the link frames: [L, 3] = (x_m, y_m, theta_rad)."""
    x0, y0, theta = spec.pose
    rotation = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    poses = [np.array([x0, y0, theta])]
    if len(spec.links) > 1:
        offset, _ = attachment(spec)
        xy = np.array([x0, y0]) + rotation @ offset
        poses.append(np.array([xy[0], xy[1], theta]))
    return np.stack(poses)


def link_surface_points(
    spec: ObjectSpec, link_poses: FloatArray, count: int, rng: np.random.Generator
) -> list[FloatArray]:
    """The true surface of each link at world poses ``link_poses`` [L, 3]: one [count, 3]
    array of world points (m) per link."""
    return [
        to_world_xy(prism_surface_points(link.polygon(), link.height_m, count, rng), pose)
        for link, pose in zip(spec.links, link_poses, strict=True)
    ]


# ---------------------------------------------------------------------------------------------
# Loading


def object_from_dict(data: Any, source: str = "") -> ObjectSpec:
    """Validate a mapping as an :class:`ObjectSpec`; errors name the YAML path of each issue."""
    if not isinstance(data, dict):
        raise ConfigError([ConfigIssue("", "an object file must be a mapping")], source)
    try:
        return ObjectSpec.model_validate(data)
    except ValidationError as error:
        raise ConfigError(validation_issues("", error, ObjectSpec), source) from None


def load_object(path: str | Path) -> ObjectSpec:
    """Read an object YAML file (safe-loaded; a missing or malformed file, or a key given
    twice, is one clear ConfigError line)."""
    return object_from_dict(read_yaml(Path(path)), str(path))


def save_object(spec: ObjectSpec, path: str | Path) -> None:
    """Write ``spec`` as YAML (loadable with :func:`load_object`)."""
    data = json.loads(spec.model_dump_json(exclude_none=True))
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")


# ---------------------------------------------------------------------------------------------
# The 120 configurations


def _random_link(rng: np.random.Generator) -> LinkSpec:
    footprint = FOOTPRINTS[int(rng.integers(len(FOOTPRINTS)))]
    polygon = footprint_polygon(footprint)
    while True:
        com = rng.uniform(polygon.min(axis=0), polygon.max(axis=0))
        if points_inside(COM_SHRINK * polygon, com[None])[0]:
            break
    return LinkSpec(
        footprint=footprint,  # type: ignore[arg-type]
        height_m=float(rng.uniform(*HEIGHT_RANGE_M)),
        mass_kg=float(rng.uniform(*MASS_RANGE_KG)),
        friction=float(rng.uniform(*FRICTION_RANGE)),
        com_m=(float(com[0]), float(com[1])),
    )


def _random_object(kind: ObjectType, index: int, rng: np.random.Generator) -> ObjectSpec:
    links = [_random_link(rng) for _ in range(1 if kind == "homogeneous" else 2)]
    joint = None
    if kind == "articulated":
        joint = JointSpec(friction_nm=float(rng.uniform(*JOINT_FRICTION_RANGE_NM)))
    pose = (
        float(rng.uniform(-0.05, 0.05)),
        float(rng.uniform(0.42, 0.48)),
        float(rng.uniform(-np.pi, np.pi)),
    )
    shapes = "_".join(link.footprint for link in links)
    return ObjectSpec(
        name=f"{kind[:5]}_{index:02d}_{shapes}", type=kind, links=links, pose=pose, joint=joint
    )


def redraw_parameters(spec: ObjectSpec, rng: np.random.Generator) -> ObjectSpec:
    """The same object (footprints, heights, pose, joint) with its parameters drawn anew as
    the object set draws them: m, f and the joint friction uniform over their ranges, each
    CoM uniform inside its footprint shrunk by :data:`COM_SHRINK`."""
    links = [
        link.model_copy(update={
            "mass_kg": float(rng.uniform(*MASS_RANGE_KG)),
            "friction": float(rng.uniform(*FRICTION_RANGE)),
            "com_m": tuple(float(v) for v in uniform_inside(COM_SHRINK * link.polygon(), 1,
                                                            rng)[0]),
        })
        for link in spec.links
    ]  # fmt: skip
    joint = None
    if spec.joint is not None:
        friction_nm = float(rng.uniform(*JOINT_FRICTION_RANGE_NM))
        joint = spec.joint.model_copy(update={"friction_nm": friction_nm})
    return spec.model_copy(update={"links": links, "joint": joint})


def generate_configurations(seed: int, per_type: int = 40) -> list[ObjectSpec]:
    """The paper's object set: ``per_type`` homogeneous, heterogeneous and articulated objects.

    Parameters are drawn uniformly from the ranges above; the same seed gives the same set.
    """
    rng = np.random.default_rng(seed)
    return [_random_object(kind, index, rng) for kind in OBJECT_TYPES for index in range(per_type)]


def split_configurations(
    specs: list[ObjectSpec], seed: int, fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)
) -> dict[str, list[str]]:
    """Stratified train/val/test split of object names (each split gets every type).

    The fractions apply per type (paper: 80 % / 10 % / 10 %), so 40 objects per type give
    32 / 4 / 4 and the 120 objects 96 / 12 / 12.
    """
    rng = np.random.default_rng(seed)
    split: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    for kind in OBJECT_TYPES:
        names = [spec.name for spec in specs if spec.type == kind]
        order = [names[i] for i in rng.permutation(len(names))]
        n_val = max(1, round(fractions[1] * len(names)))
        n_test = max(1, round(fractions[2] * len(names)))
        split["val"] += order[:n_val]
        split["test"] += order[n_val : n_val + n_test]
        split["train"] += order[n_val + n_test :]
    return split


def interleave_types(paths: Sequence[Path]) -> list[Path]:
    """Object files in turns of their type (homogeneous, heterogeneous, articulated), each type
    in its given order, so that the first N of them cover every type."""
    by_type = {kind: [p for p in paths if load_object(p).type == kind] for kind in OBJECT_TYPES}
    turns = itertools.zip_longest(*by_type.values())
    return [path for turn in turns for path in turn if path is not None]


def write_configurations(seed: int, out_dir: str | Path) -> dict[str, list[str]]:
    """Write one YAML per generated object and ``split.json`` into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    specs = generate_configurations(seed)
    for spec in specs:
        save_object(spec, out / f"{spec.name}.yaml")
    split = split_configurations(specs, seed)
    (out / "split.json").write_text(json.dumps(split, indent=2), encoding="utf-8")
    return split
