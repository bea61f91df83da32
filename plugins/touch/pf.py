"""``touch.pf``: a particle filter over (object class, 6D pose) from touches (paper 2, III-C
to III-F).

Per touch (Algorithm 1): weigh the particles by the new observation (contact: signed
distance and normal, eq. 12-16; miss: negative information, eq. 17-18), resample (stochastic
universal sampling, with a small roughening of duplicated particles), propose new particles
from point-pair features of the new contact paired with a fixed-size selection of earlier
contacts (Drost 2010 hash tables over each class's Poisson-disk samples), weigh them with the
approximation of eq. 25-27, and report the class probabilities, the maximum-likelihood
(class, pose) and the known/novel decision of eq. 28.

Observations are moved into each particle's object frame by its inverse pose and looked up in
the signed distance grids of all classes at once (``ClassGrids``), and the proposals of all
classes are aligned and weighed together.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import Field, ValidationInfo, field_validator
from scipy.spatial.transform import Rotation
from scipy.special import log_ndtr
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.plugins.touch.library import KNOWN, require_shape_in_skill, resolve_shape, shape_name
from vistac.plugins.touch.meshes import (
    GridSDF,
    Mesh,
    apply_pose,
    split_normals,
    transform_sdf,
    trilinear,
)
from vistac.plugins.touch.ppf import PpfTable, Quantisation, align_pairs, point_pair_features
from vistac.plugins.touch.types import MlePrior
from vistac.types import FloatArray

log = logging.getLogger(__name__)

SURFACE_SAMPLES = 400
"""Surface samples per class published for exploration (eq. 42) and metrics."""

FAR_SIGMAS = 8.5
"""A free-space point surely farther than this many ``sigma_distance_m`` from a particle's
surface is not interpolated in its grid and gets log likelihood 0 (eq. 18 gives between
log Phi(8.5) = -9.5e-18 and 0, which rounds away in a particle's summed log weight)."""


def contact_log_likelihood(
    distance_m: FloatArray, normal_error: FloatArray, sigma_distance_m: float, sigma_normal: float
) -> FloatArray:
    """log p(contact | x) - log p_max (eq. 14-16): distance [...] predicted at the contact and
    normal_error [...] = |n_observed - n_predicted|; 0 for an exact contact."""
    return -0.5 * (distance_m / sigma_distance_m) ** 2 - 0.5 * (normal_error / sigma_normal) ** 2


def miss_log_likelihood(distance_m: FloatArray, sigma_distance_m: float) -> FloatArray:
    """log p(no contact | x) (eq. 17-18): log of (1 + erf(d / (sqrt(2) sigma))) / 2 at the
    predicted signed distance d [...] of a point the probe reached without touching."""
    return np.asarray(log_ndtr(distance_m / sigma_distance_m), dtype=np.float64)


def stochastic_universal_sampling(weights: FloatArray, count: int, rng: np.random.Generator) -> Any:
    """Indices [count] drawn with one random offset and equal spacing (sorted)."""
    positions = (rng.uniform() + np.arange(count)) / count
    cumulative = np.cumsum(weights / weights.sum())
    cumulative[-1] = 1.0
    return np.searchsorted(cumulative, positions, side="right").clip(0, len(weights) - 1)


@dataclass
class ShapeClass:
    """One known class: its mesh, SDF grid, PPF table and published surface samples."""

    name: str
    mesh: Mesh
    grid: GridSDF
    table: PpfTable
    surface: FloatArray
    surface_normals: FloatArray


class ClassGrids:
    """The signed distance grids (``GridSDF``) of all classes side by side along x, one volume
    of four channels (distance, normal x, y, z), so that the points of particles of mixed
    classes are interpolated in one ``trilinear`` call. Each class's points are clamped to its
    own grid box, so the values are its ``GridSDF``'s (to rounding in the last bits of the grid
    coordinates, which are shifted by the class's whole-cell offset along x)."""

    def __init__(self, grids: list[GridSDF]) -> None:
        shapes = np.array([grid.shape for grid in grids])  # [C, 3] cells per axis
        self._x_offset = np.r_[0, np.cumsum(shapes[:-1, 0])].astype(np.float64)  # [C] cells
        self._top = (shapes - 1).astype(np.float64)  # [C, 3] last grid coordinate
        self._origin_m = np.array([grid.origin_m for grid in grids])  # [C, 3]
        self._step_m = np.array([grid.step_m for grid in grids])  # [C]
        volumes = np.zeros((4, shapes[:, 0].sum(), *shapes[:, 1:].max(axis=0)), np.float64)
        for grid, start, (x, y, z) in zip(grids, self._x_offset.astype(int), shapes, strict=True):
            volumes[:, start : start + x, :y, :z] = grid.volumes
        self._volumes = torch.from_numpy(volumes)
        self._face_min_m = np.array([_face_min(grid.volumes[0]) for grid in grids])  # [C]

    def _coordinates(self, cls: Any, local_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Stacked grid coordinates [N * K, 3] of points local_m [N, K, 3] (object frame of
        class cls [N]), clamped to their class's grid, and each point's distance to that grid
        box [N, K] in m."""
        step_m = self._step_m[cls][:, None, None]
        scaled = (local_m - self._origin_m[cls][:, None]) / step_m
        clamped = np.clip(scaled, 0.0, self._top[cls][:, None])
        outside_m = np.linalg.norm(scaled - clamped, axis=-1) * step_m[..., 0]
        coordinates = clamped.reshape(-1, 3)  # a view of the fresh clipped array
        coordinates[:, 0] += np.repeat(self._x_offset[cls], local_m.shape[1])
        return coordinates, outside_m

    def distance(self, cls: Any, local_m: FloatArray, far_m: float = np.inf) -> FloatArray:
        """Signed distance [N, K] in m of points local_m [N, K, 3] in the frame of class
        cls [N] (as ``GridSDF.distance``). A point outside its grid box whose distance is at
        least ``far_m`` by the bound (distance to the box + the smallest distance on the box's
        faces) gets that lower bound instead of being interpolated."""
        coordinates, outside_m = self._coordinates(cls, local_m)
        distance_m = (outside_m + self._face_min_m[cls][:, None]).ravel()
        near = np.flatnonzero(distance_m < far_m)
        distance = trilinear(self._volumes[:1], coordinates[near])[0]
        distance_m[near] = distance + outside_m.ravel()[near]
        return distance_m.reshape(outside_m.shape)

    def __call__(self, cls: Any, local_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Signed distance [N, K] in m and unit outward normals [N, K, 3] of points local_m
        [N, K, 3] in the frame of class cls [N] (as ``GridSDF.__call__``)."""
        coordinates, outside_m = self._coordinates(cls, local_m)
        return split_normals(trilinear(self._volumes, coordinates), outside_m, outside_m.shape)


@dataclass
class Particles:
    """class index [N], rotation [N, 3, 3] and translation [N, 3] (world_from_object),
    log weight [N], log copies [N]: the log of how many resampled copies a particle's row
    stands for (0 for a roughened copy or a new proposal), so that its posterior mass, which
    resampling spreads over equal weights, still ranks it, and log evidence [N]: the log
    likelihood of all data so far at the particle's pose, NaN until it is first needed (an MLE
    candidate), then kept up to date by each step's weighing."""

    cls: Any
    rotation: FloatArray
    translation: FloatArray
    log_weight: FloatArray
    log_copies: FloatArray
    log_evidence: FloatArray

    @classmethod
    def empty(cls) -> Particles:
        none = np.zeros(0)
        return cls(np.zeros(0, int), np.zeros((0, 3, 3)), np.zeros((0, 3)), none, none, none)

    def __len__(self) -> int:
        return len(self.cls)

    def take(self, index: Any) -> Particles:
        return Particles(*(getattr(self, field.name)[index] for field in fields(self)))

    def concat(self, other: Particles) -> Particles:
        return Particles(
            *(np.concatenate([getattr(self, f.name), getattr(other, f.name)]) for f in fields(self))
        )

    def pose(self, index: int) -> FloatArray:
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = self.rotation[index], self.translation[index]
        return pose


class TouchParticleFilter(Component):
    """Recognition and 6D pose estimation of a known object from touches."""

    kind = "touch_estimator"

    class Config(ComponentConfig):
        classes: list[str] = Field(
            default_factory=lambda: list(KNOWN),
            description="known classes: library names (0.2 m across, centred) or mesh file "
            "paths, read as saved (metres, the file's own object frame, as learn_shape saves "
            "them; not rescaled). A class is named by its library name or file stem; the names "
            "must be unique",
        )

        @field_validator("classes")
        @classmethod
        def _names_unique(cls, specs: list[str], info: ValidationInfo) -> list[str]:
            """At least one class, each a library name or (in a skill) a mesh file that exists,
            relative to the skill's folder, with unique names: checked before anything is
            built."""
            if not specs:
                raise ValueError("touch.pf needs at least one known class")
            for spec in specs:
                require_shape_in_skill(spec, (info.context or {}).get("skill_dir"))
            clash = _name_clash(specs)
            if clash is not None:
                raise ValueError(clash)
            return specs

        feature_points: int = Field(200, ge=10, description="Poisson-disk samples per class")
        distance_step_m: float = Field(0.015, gt=0, description="PPF distance bin")
        angle_step_deg: float = Field(30.0, gt=0, le=90, description="PPF angle bin")
        sigma_distance_m: float = Field(0.006, gt=0)
        sigma_normal: float = Field(0.5, gt=0)
        resample_count: int = Field(1000, gt=0, description="particles kept by resampling")
        proposals_per_class: int = Field(500, ge=0, description="new particles per class and step")
        pair_points: int = Field(4, ge=1, description="earlier contacts paired with a new one")
        propose_below: float = Field(
            0.98,
            gt=0,
            le=1,
            description="propose only while the MLE's mean contact likelihood ratio is below this",
        )
        known_contact_ratio: float = Field(0.6, gt=0, le=1, description="rho of eq. 28")
        known_miss_likelihood: float = Field(0.5, gt=0, le=1, description="gamma of eq. 28")
        decide_after_contacts: int = Field(10, ge=2, description="known/novel from this many")
        roughen_position_m: float = Field(0.002, ge=0)
        roughen_rotation_deg: float = Field(1.5, ge=0)
        mle_candidates: int = Field(
            32, ge=1, description="top-weighted particles checked on all data for the MLE"
        )
        workspace_centre_m: tuple[float, float, float] = (0.0, 0.5, 0.3)
        workspace_half_extent_m: float = Field(0.2, gt=0, description="the object is inside")
        free_path_step_m: float = Field(
            0.025,
            gt=0,
            description="negative information every this far along the free part "
            "of each probe path inside the workspace",
        )
        contact_margin_m: float = Field(
            0.01, ge=0, description="free path ends this far before a contact"
        )

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self._rng = ctx.rng("touch_pf")
        quantisation = Quantisation(config.distance_step_m, np.deg2rad(config.angle_step_deg))
        start_s = time.perf_counter()
        self.classes = [self._build_class(spec, quantisation) for spec in config.classes]
        self.build_s = time.perf_counter() - start_s
        self.table_build_s = sum(c.table.build_s for c in self.classes)
        self._grids = ClassGrids([c.grid for c in self.classes])
        self._anchor_ll = [self._model_log_likelihoods(i) for i in range(len(self.classes))]
        self.particles = Particles.empty()
        self.contacts = np.zeros((0, 3))
        self.normals = np.zeros((0, 3))
        self.miss_points = np.zeros((0, 3))
        self.free_points = np.zeros((0, 3))
        self.max_particle_count = 0
        self.steps = 0
        self._mle: int | None = None
        self._mle_log_likelihood = np.zeros(0)

    def _build_class(self, spec: str, quantisation: Quantisation) -> ShapeClass:
        mesh = resolve_shape(spec, self.ctx.skill_dir)
        points, normals = _feature_samples(mesh, self.config.feature_points)
        surface, surface_normals = mesh.surface_samples(SURFACE_SAMPLES, seed=1)
        return ShapeClass(
            mesh.name,
            mesh,
            mesh.grid_sdf,
            PpfTable(points, normals, quantisation),
            surface,
            surface_normals,
        )

    def _model_log_likelihoods(self, index: int) -> FloatArray:
        """Contact log likelihoods [M] of class ``index``'s PPF model points with their normals
        (where a proposal puts the contact it was aligned on)."""
        table = self.classes[index].table
        distance, predicted = self._grids(np.array([index]), table.points[None])
        error = np.linalg.norm(table.normals - predicted[0], axis=-1)
        return contact_log_likelihood(
            distance[0], error, self.config.sigma_distance_m, self.config.sigma_normal
        )

    @property
    def class_names(self) -> list[str]:
        return [c.name for c in self.classes]

    # --- likelihood ------------------------------------------------------------------

    def log_likelihoods(
        self, particles: Particles, points: FloatArray, normals: FloatArray | None
    ) -> FloatArray:
        """Per particle and point [N, K]: contact log likelihoods (eq. 16) when ``normals``
        is given, else negative-information log likelihoods (eq. 18). ``points`` and
        ``normals``: [K, 3], or [N, K, 3] for points of each particle's own."""
        if points.shape[-2] == 0 or len(particles) == 0:
            return np.zeros((len(particles), points.shape[-2]))
        rotation = particles.rotation
        local = (points - particles.translation[:, None]) @ rotation  # [N, K, 3]
        if normals is None:
            sigma_m = self.config.sigma_distance_m
            distance = self._grids.distance(particles.cls, local, FAR_SIGMAS * sigma_m)
            near = distance < FAR_SIGMAS * sigma_m
            result = np.zeros(distance.shape)
            result[near] = miss_log_likelihood(distance[near], sigma_m)
            return result
        distance, predicted = self._grids(particles.cls, local)
        error = np.linalg.norm(normals @ rotation - predicted, axis=-1)
        return contact_log_likelihood(
            distance, error, self.config.sigma_distance_m, self.config.sigma_normal
        )

    def _all_data(self, particles: Particles) -> tuple[FloatArray, FloatArray]:
        """Per particle: contact log likelihoods [N, K] and free-space log likelihoods [N, J]."""
        return (
            self.log_likelihoods(particles, self.contacts, self.normals),
            self.log_likelihoods(particles, self.free_points, None),
        )

    def free_path(self, start_m: FloatArray, end_m: FloatArray) -> FloatArray:
        """Points [J, 3] every ``free_path_step_m`` along start -> end inside the workspace
        cube, the end included when inside: places the probe passed without contact."""
        length_m = float(np.linalg.norm(end_m - start_m))
        steps = np.arange(length_m, 0.0, -self.config.free_path_step_m)[::-1]
        points = start_m + np.outer(steps / max(length_m, 1e-12), end_m - start_m)
        centre = np.asarray(self.config.workspace_centre_m)
        inside = np.all(np.abs(points - centre) <= self.config.workspace_half_extent_m, axis=1)
        return np.asarray(points[inside], dtype=np.float64)

    # --- the filter step -------------------------------------------------------------

    def update(
        self,
        start_m: FloatArray,
        target_m: FloatArray,
        contact: tuple[FloatArray, FloatArray] | None,
    ) -> dict[str, Any]:
        """One touch from ``start_m`` [3] to ``target_m`` [3]: a contact (point [3], normal
        [3]) or None (the probe reached the target untouched: negative information there)."""
        self.steps += 1
        start, target = (
            np.asarray(start_m, dtype=np.float64),
            np.asarray(target_m, dtype=np.float64),
        )
        if contact is None:
            self.miss_points = np.vstack([self.miss_points, target[None]])
            free = self.free_path(start, target)
        else:
            point, normal = (np.asarray(v, dtype=np.float64) for v in contact)
            self.contacts = np.vstack([self.contacts, point[None]])
            self.normals = np.vstack([self.normals, (normal / np.linalg.norm(normal))[None]])
            self._weigh(self.contacts[-1:], self.normals[-1:])
            direction = (point - start) / max(float(np.linalg.norm(point - start)), 1e-12)
            free = self.free_path(start, point - self.config.contact_margin_m * direction)
        self.free_points = np.vstack([self.free_points, free])
        self._weigh(free, None)
        self._resample()
        self._find_mle()
        if contact is not None and len(self.contacts) >= 2 and self._needs_proposals():
            self._propose()
            self._find_mle()
        self.max_particle_count = max(self.max_particle_count, len(self.particles))
        return self.estimate()

    def _weigh(self, points: FloatArray, normals: FloatArray | None) -> None:
        if len(self.particles):
            log_likelihood = self.log_likelihoods(self.particles, points, normals).sum(axis=1)
            self.particles.log_weight = self.particles.log_weight + log_likelihood
            self.particles.log_evidence = self.particles.log_evidence + log_likelihood

    def _normalised_weights(self) -> FloatArray:
        log_weight = self.particles.log_weight - self.particles.log_weight.max()
        weights = np.exp(log_weight)
        return np.asarray(weights / weights.sum(), dtype=np.float64)

    def _resample(self) -> None:
        """SUS down to ``resample_count`` particles with equal weights; duplicates are
        roughened (the first copy of each particle stays where it was)."""
        if len(self.particles) == 0:
            return
        count = min(self.config.resample_count, len(self.particles))
        index = stochastic_universal_sampling(self._normalised_weights(), count, self._rng)
        self.particles = self.particles.take(index)
        self.particles.log_weight = np.full(count, -np.log(count))
        first = np.r_[True, index[1:] != index[:-1]]  # SUS indices come sorted
        self.particles.log_copies = np.zeros(count)
        self.particles.log_copies[first] = np.log(np.diff(np.r_[np.flatnonzero(first), count]))
        self._roughen(np.flatnonzero(~first))

    def _roughen(self, rows: Any) -> None:
        if len(rows) == 0:
            return
        turn = np.deg2rad(self.config.roughen_rotation_deg)
        spin = Rotation.from_rotvec(self._rng.normal(0.0, turn, (len(rows), 3))).as_matrix()
        self.particles.rotation[rows] = spin @ self.particles.rotation[rows]
        self.particles.translation[rows] += self._rng.normal(
            0.0, self.config.roughen_position_m, (len(rows), 3)
        )
        self.particles.log_evidence[rows] = np.nan

    def _find_mle(self) -> None:
        """The MLE particle: the best, over all data, of the candidates of most posterior mass
        (weight times resampled copies). Only candidates without a log evidence yet are
        evaluated on all data."""
        if len(self.particles) == 0:
            self._mle = None
            return
        mass = self.particles.log_weight + self.particles.log_copies
        top = np.argsort(-mass)[: self.config.mle_candidates]
        evidence = self.particles.log_evidence
        unknown = top[np.isnan(evidence[top])]
        if len(unknown):
            contact_ll, miss_ll = self._all_data(self.particles.take(unknown))
            evidence[unknown] = contact_ll.sum(axis=1) + miss_ll.sum(axis=1)
        self._mle = int(top[np.argmax(evidence[top])])
        contact_ll, miss_ll = self._all_data(self.particles.take([self._mle]))
        self._mle_contact_ll, self._mle_miss_ll = contact_ll[0], miss_ll[0]

    def _mle_total(self) -> float:
        return float(self._mle_contact_ll.sum() + self._mle_miss_ll.sum())

    def _needs_proposals(self) -> bool:
        if self._mle is None:
            return True
        return float(np.exp(self._mle_contact_ll).mean()) < self.config.propose_below

    def _pair_partners(self) -> Any:
        """Indices of earlier contacts paired with the newest: sorted by distance to it,
        split into ``pair_points`` segments, the first of each (III-E)."""
        earlier = len(self.contacts) - 1
        distance = np.linalg.norm(self.contacts[:earlier] - self.contacts[-1], axis=1)
        order = np.argsort(distance)
        segments = np.array_split(order, min(self.config.pair_points, earlier))
        return np.array([segment[0] for segment in segments])

    def _propose(self) -> None:
        proposals = self._proposals()
        if proposals is not None:
            new, counts, subset_ll = proposals
            self._weigh_proposals(new, counts, subset_ll)
            self.particles = self.particles.concat(new)
            self.particles.log_weight -= self.particles.log_weight.max()

    def _proposals(self) -> tuple[Particles, Any, FloatArray] | None:
        """New particles from the newest contact paired with earlier ones (III-E), their count
        per class [C] and their log likelihoods on the paired contacts [N]; None without a
        matching model pair."""
        partners = self._pair_partners()
        newest = len(self.contacts) - 1
        first = np.r_[np.full(len(partners), newest), partners]
        second = np.r_[partners, np.full(len(partners), newest)]
        points, normals = self.contacts, self.normals
        keys = self.classes[0].table.quantisation.keys(
            point_pair_features(points[first], normals[first], points[second], normals[second])
        )
        pairs = [self._class_pairs(shape, keys) for shape in self.classes]
        counts = np.array([len(query) for _, _, query in pairs])
        if counts.sum() == 0:
            return None
        new = self._aligned(pairs, counts, first, second)
        query = np.concatenate([q for _, _, q in pairs])
        anchor_ll = np.concatenate(
            [ll[f] for ll, (f, _, _) in zip(self._anchor_ll, pairs, strict=True)]
        )
        return new, counts, self._subset_log_likelihoods(new, partners, query, anchor_ll)

    def _class_pairs(self, shape: ShapeClass, keys: Any) -> tuple[Any, Any, Any]:
        """Model pairs of ``shape`` matching the query keys [Q], at most
        ``proposals_per_class`` of them: (first model point [P], second [P], query [P])."""
        model_first, model_second, query = shape.table.lookup(keys)
        if len(query) > self.config.proposals_per_class:
            keep = self._rng.choice(len(query), self.config.proposals_per_class, replace=False)
            model_first, model_second, query = model_first[keep], model_second[keep], query[keep]
        return model_first, model_second, query

    def _aligned(
        self, pairs: list[tuple[Any, Any, Any]], counts: Any, first: Any, second: Any
    ) -> Particles:
        """New particles [sum(counts)], class by class: each class's model pairs (``pairs``,
        counts [C] of them) aligned onto the contact pairs (first [Q], second [Q]) they match."""
        tables = [shape.table for shape in self.classes]
        first_model = [(t, f) for t, (f, _, _) in zip(tables, pairs, strict=True)]
        second_model = [(t, s) for t, (_, s, _) in zip(tables, pairs, strict=True)]
        query = np.concatenate([q for _, _, q in pairs])
        poses = align_pairs(
            np.concatenate([t.points[f] for t, f in first_model]),
            np.concatenate([t.normals[f] for t, f in first_model]),
            np.concatenate([t.points[s] for t, s in second_model]),
            self.contacts[first[query]],
            self.normals[first[query]],
            self.contacts[second[query]],
        )
        cls, count = np.repeat(np.arange(len(self.classes)), counts), len(poses)
        return Particles(
            cls, poses[:, :3, :3], poses[:, :3, 3], np.zeros(count), np.zeros(count),
            np.full(count, np.nan),
        )  # fmt: skip

    def _subset_log_likelihoods(
        self, new: Particles, partners: Any, query: Any, anchor_ll: FloatArray
    ) -> FloatArray:
        """Log likelihoods [N] of new particles on the contacts paired (partners [P], then the
        newest). The contact of each particle's pair that it put onto a model point (the
        first of query [N]) is not looked up: it gets that point's ``anchor_ll`` [N]."""
        count, subset = len(partners), np.r_[partners, len(self.contacts) - 1]
        anchor = np.where(query < count, count, query - count)  # [N] column in the subset
        others = np.array([np.delete(np.arange(count + 1), a) for a in range(count + 1)])
        columns = others[anchor]  # [N, P]
        log_likelihood = np.empty((len(new), count + 1))
        rows = np.arange(len(new))
        log_likelihood[rows[:, None], columns] = self.log_likelihoods(
            new, self.contacts[subset][columns], self.normals[subset][columns]
        )
        log_likelihood[rows, anchor] = anchor_ll
        return np.asarray(log_likelihood.sum(axis=1), dtype=np.float64)

    def _weigh_proposals(self, new: Particles, counts: Any, subset_ll: FloatArray) -> None:
        """Eq. 27 weights of new particles (counts [C] per class, in class order) from their
        log likelihoods on the paired contacts, subset_ll [N]: each class's best there is
        weighed on all data, the others relative to it."""
        ends = np.cumsum(counts)
        proposed = np.flatnonzero(counts)
        best = np.array([ends[i] - counts[i] + np.argmax(subset_ll[ends[i] - counts[i] : ends[i]])
                         for i in proposed])  # fmt: skip
        contact_ll, miss_ll = self._all_data(new.take(best))
        best_total = np.zeros(len(counts))
        new.log_evidence[best] = contact_ll.sum(axis=1) + miss_ll.sum(axis=1)
        best_total[proposed] = new.log_evidence[best]
        best_subset = np.zeros(len(counts))
        best_subset[proposed] = subset_ll[best]
        reference = self._reference_log_weight()
        new.log_weight = reference + best_total[new.cls] + (subset_ll - best_subset[new.cls])

    def _reference_log_weight(self) -> float:
        """log(w_mle) - log L(all data | x_mle) of eq. 27 (0 before there is an MLE)."""
        if self._mle is None:
            return 0.0
        return float(self.particles.log_weight[self._mle]) - self._mle_total()

    # --- outputs -------------------------------------------------------------------------

    def class_probabilities(self) -> dict[str, float]:
        """{class name: posterior probability}; uniform before there are particles."""
        if len(self.particles) == 0:
            return {name: 1.0 / len(self.classes) for name in self.class_names}
        weights = np.bincount(self.particles.cls, self._normalised_weights(), len(self.classes))
        return {name: float(w) for name, w in zip(self.class_names, weights, strict=True)}

    def mle_pose(self) -> FloatArray | None:
        """world_from_object [4, 4] of the MLE particle, or None."""
        return None if self._mle is None else self.particles.pose(self._mle)

    def mle_class(self) -> ShapeClass | None:
        return None if self._mle is None else self.classes[int(self.particles.cls[self._mle])]

    def known(self) -> bool | None:
        """Eq. 28: mean contact likelihood ratio >= rho and mean miss likelihood >= gamma;
        None until ``decide_after_contacts`` contacts."""
        if self._mle is None or len(self.contacts) < self.config.decide_after_contacts:
            return None
        contact_ok = float(np.exp(self._mle_contact_ll).mean()) >= self.config.known_contact_ratio
        if len(self.miss_points) == 0:
            return contact_ok
        miss_ll = self.log_likelihoods(self.particles.take([self._mle]), self.miss_points, None)
        return bool(
            contact_ok and float(np.exp(miss_ll).mean()) >= self.config.known_miss_likelihood
        )

    def mle_prior(self) -> MlePrior | None:
        """The MLE (class, pose) as a prior shape in the world frame, or None."""
        shape, pose = self.mle_class(), self.mle_pose()
        if shape is None or pose is None:
            return None
        return MlePrior(
            class_name=shape.name,
            probability=self.class_probabilities()[shape.name],
            world_from_object=pose,
            vertices_m=apply_pose(pose, shape.mesh.vertices_m),
            triangles=shape.mesh.triangles,
            sdf=transform_sdf(shape.mesh.sdf(), pose),
        )

    def estimate(self) -> dict[str, Any]:
        """The current belief: JSON-friendly entries plus ``mle_surface_m`` /
        ``mle_surface_normals`` ([S, 3] arrays, world frame) for exploration."""
        shape, pose = self.mle_class(), self.mle_pose()
        result: dict[str, Any] = {
            "class_probabilities": self.class_probabilities(),
            "mle_class": None if shape is None else shape.name,
            "mle_pose": None if pose is None else pose.tolist(),
            "particle_count": len(self.particles),
            "max_particle_count": self.max_particle_count,
            "known": self.known(),
            "log_evidence": None if self._mle is None else self._mle_total(),
            "contact_likelihood": None
            if self._mle is None
            else float(np.exp(self._mle_contact_ll).mean()),
            "contacts": self.contacts.tolist(),
            "normals": self.normals.tolist(),
            "misses": len(self.miss_points),
            "steps": self.steps,
        }
        if shape is not None and pose is not None:
            result["mle_surface_m"] = apply_pose(pose, shape.surface)
            result["mle_surface_normals"] = shape.surface_normals @ pose[:3, :3].T
        return result


def _name_clash(specs: list[str]) -> str | None:
    """What is wrong when two class specs resolve to the same class name (the class
    probabilities are keyed by name), or None."""
    first: dict[str, str] = {}
    for spec in specs:
        name = shape_name(spec)
        if name in first:
            suffix = Path(spec).suffix or Path(first[name]).suffix or ".ply"
            return (
                f"classes {first[name]!r} and {spec!r} are both named {name!r} (a mesh file's "
                "class name is its file stem); list each class once and rename a mesh file "
                f"whose stem repeats another class's name, e.g. to {name}_2{suffix}"
            )
        first[name] = spec
    return None


def _face_min(distance_m: FloatArray) -> float:
    """The smallest value [m] on the six faces of a grid of distances [X, Y, Z]."""
    faces = (distance_m[[0, -1]], distance_m[:, [0, -1]], distance_m[:, :, [0, -1]])
    return float(min(face.min() for face in faces))


def _feature_samples(mesh: Mesh, count: int) -> tuple[FloatArray, FloatArray]:
    """``count`` Poisson-disk samples with normals for the PPF table (object frame)."""
    return mesh.surface_samples(count, seed=0)
