"""Click-free correspondence between labelled robot-space spheres and unlabelled image detections.

The robot side is ordered (sphere k is hole k of the phantom, N points); the
image side is an unordered set of M detections, some spheres missing and some
detections spurious.  ICP alone only converges from within about half the hole
pitch (≈ 9° of rotation, research/registration-ecosystem.md §1.7), so the pose
is found globally first:

1. a few *base triples* of robot spheres are chosen: long, rare edges (few
   image pairs share their length) and disjoint vertices, so that up to a few
   missing spheres cannot remove all of them;
2. for each base triple (a, b, c), every ordered image pair (i, j) whose
   distance matches |ab| within ``pair_tol_mm`` is found by a ``searchsorted``
   on the sorted image distances; each third image point k must match |ac| and
   |bc| too (pairwise distances are invariant under rigid motion);
3. each consistent image triple gives a proper rigid transform (Kabsch with the
   determinant fix, :func:`registration.matching.rigid.fit_rigid_batch`), first scored on
   a few far-apart *probe* spheres, then the best ones on every sphere: the
   number of robot spheres that land within ``gate_mm`` of a detection
   (``scipy.spatial.cKDTree``).  The 3-point transforms are accurate to a
   fraction of a mm, well inside ICP's 7.5 mm starting gate, so they are not
   refit here;
4. hypotheses are merged into *distinct* poses (rotations differ by more than
   ``distinct_rotation_deg`` or the robot centroid lands more than
   ``distinct_translation_mm`` apart); the search stops early once the best
   pose has been found from ``min_agreeing`` independent base triples.

The caller (:mod:`registration.matching.register`) refines the best and the runner-up
poses with ICP and refuses an ambiguous result.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from registration.arrays import F64
from registration.matching.rigid import fit_rigid_batch, rotation_difference_deg

log = logging.getLogger(__name__)

I64 = NDArray[np.int64]

MIN_EDGE_FRACTION: Final = 0.45
"""Base-triple edges are at least this fraction of the robot set's diameter: long edges make the
3-point rotation accurate (error ≈ σ·√2 / edge) so its inlier count is meaningful."""

DEFAULT_N_PROBES: Final = 8
"""Probe spheres scored for every 3-point hypothesis before full scoring (cheap pre-filter)."""

DEFAULT_MAX_SCORED: Final = 48
"""Hypotheses per base triple that are scored on every sphere (the best by probe hits)."""

DEFAULT_DISTINCT_ROTATION_DEG: Final = 5.0
"""Two poses are distinct if their rotations differ by more than this: the grid's symmetries are
≥ 90° apart and 3-point pose noise is ≈ 0.1°, so anything from 1° to 45° separates them; 5° is
the value :class:`registration.matching.register.RegistrationParams` has always used (one source of truth)."""

DEFAULT_DISTINCT_TRANSLATION_MM: Final = 3.0
"""... or if the robot centroid lands more than this apart (one pitch is 15 mm; pose noise ≪ 1 mm)."""

DEFAULT_MAX_HYPOTHESES: Final = 12
"""Distinct hypotheses returned at most: the 8 proper symmetries of the full grid plus margin."""

MIN_HYPOTHESIS_INLIERS: Final = 3
"""A hypothesis with fewer inliers than its own base triple (3 points) is noise and is dropped."""

COLLINEAR_AREA_FRACTION: Final = 1e-6
"""A base triple whose doubled triangle area is below this × diameter² is collinear (numerical
zero for mm coordinates: at a 100 mm diameter it is a 0.01 mm² triangle) and is skipped."""


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """A candidate pose from one consistent triple, refit on its inliers.

    Attributes
    ----------
    image_from_robot : ndarray, shape (4, 4), float64
    n_inliers : int
        Robot spheres landing within the gate of a detection.
    rms_mm : float
        RMS distance of those inliers (mm).
    support : int
        Number of independent base triples that produced this pose.
    """

    image_from_robot: F64
    n_inliers: int
    rms_mm: float
    support: int = 1
    base_triples: tuple[tuple[int, int, int], ...] = field(default=())


def pairwise_distances(points_mm: F64) -> F64:
    """(N, N) Euclidean distance matrix in mm."""
    diff = points_mm[:, None, :] - points_mm[None, :, :]
    return np.asarray(np.sqrt(np.einsum("ijk,ijk->ij", diff, diff)), dtype=np.float64)


def farthest_point_order(points_mm: F64, start: int = 0, count: int | None = None) -> I64:
    """Greedy farthest-point ordering of the first ``count`` point indices (for well-spread probes)."""
    n = len(points_mm) if count is None else min(count, len(points_mm))
    order = np.empty(n, dtype=np.int64)
    order[0] = start
    d = np.linalg.norm(points_mm - points_mm[start], axis=1)
    for k in range(1, n):
        nxt = int(np.argmax(d))
        order[k] = nxt
        d = np.minimum(d, np.linalg.norm(points_mm - points_mm[nxt], axis=1))
    return order


MIN_BASE_TRIPLES: Final = 2
"""Fewer eligible triples than this (a small or elongated set) relaxes the edge-length rule."""


def choose_base_triples(
    robot_mm: F64, d_robot: F64, image_pair_dist_sorted: F64, pair_tol_mm: float, max_triples: int
) -> list[tuple[int, int, int]]:
    """Robot triples with long, rare edges and (as far as possible) disjoint vertices.

    Edge (a, b) is the one with the fewest image pairs of matching length, so
    it gets the ``searchsorted`` look-up; c maximises the triangle area among
    points whose edges to a and b are long as well.  Every edge must be matched by at least one
    image pair (so the triples are chosen among what the image shows: a phantom partly outside
    the field of view keeps only its imaged part's lengths), and at least
    :data:`MIN_EDGE_FRACTION` of the smaller of the robot set's and the image set's diameters;
    a set with fewer than :data:`MIN_BASE_TRIPLES` such triples (a few spheres, far apart) is
    retried with half that fraction, then with none.
    """
    triples: list[tuple[int, int, int]] = []
    for fraction in (MIN_EDGE_FRACTION, MIN_EDGE_FRACTION / 2.0, 0.0):
        triples = _base_triples(robot_mm, d_robot, image_pair_dist_sorted, pair_tol_mm, max_triples, fraction)
        if len(triples) >= MIN_BASE_TRIPLES:
            break
    return triples


def _base_triples(
    robot_mm: F64,
    d_robot: F64,
    image_pair_dist_sorted: F64,
    pair_tol_mm: float,
    max_triples: int,
    min_edge_fraction: float,
) -> list[tuple[int, int, int]]:
    n = len(robot_mm)
    if n < 3:
        return []
    iu, ju = np.triu_indices(n, 1)
    lengths = d_robot[iu, ju]
    lo = np.searchsorted(image_pair_dist_sorted, lengths - pair_tol_mm, side="left")
    hi = np.searchsorted(image_pair_dist_sorted, lengths + pair_tol_mm, side="right")
    rarity = hi - lo
    # Long relative to what the image shows: a phantom half outside the field of view has no image
    # pair as long as the robot set's diameter, and an edge no image pair matches yields nothing.
    image_diameter = float(image_pair_dist_sorted[-1]) if len(image_pair_dist_sorted) else 0.0
    diameter = min(float(lengths.max()), image_diameter + pair_tol_mm)
    seen = np.zeros((n, n), dtype=bool)
    seen[iu, ju] = seen[ju, iu] = rarity > 0
    eligible = (lengths >= min_edge_fraction * diameter) & (rarity > 0)
    # rare first, long second
    order = np.lexsort((-lengths, rarity))
    order = order[eligible[order]]
    used = np.zeros(n, dtype=bool)
    triples: list[tuple[int, int, int]] = []
    for allow_reuse in (False, True):
        for e in order:
            if len(triples) >= max_triples:
                return triples
            a, b = int(iu[e]), int(ju[e])
            if not allow_reuse and (used[a] or used[b]):
                continue
            ok = (d_robot[a] >= min_edge_fraction * diameter) & (d_robot[b] >= min_edge_fraction * diameter)
            ok &= seen[a] & seen[b]
            if not allow_reuse:
                ok &= ~used
            ok[[a, b]] = False
            cands = np.flatnonzero(ok)
            if len(cands) == 0:
                continue
            area = np.linalg.norm(np.cross(robot_mm[b] - robot_mm[a], robot_mm[cands] - robot_mm[a]), axis=1)
            c = int(cands[int(np.argmax(area))])
            if area.max() < COLLINEAR_AREA_FRACTION * diameter**2:
                continue  # collinear
            t = (a, b, c)
            if any(set(t) == set(s) for s in triples):
                continue
            triples.append(t)
            used[[a, b, c]] = True
    return triples


def _count_inliers(
    transforms: F64, points_mm: F64, tree: cKDTree, gate_mm: float
) -> tuple[NDArray[np.int64], F64]:
    """Inlier counts and inlier RMS (mm) of each (H, 4, 4) transform applied to (P, 3) points."""
    mapped = np.einsum("hij,pj->hpi", transforms[:, :3, :3], points_mm) + transforms[:, None, :3, 3]
    d, _ = tree.query(mapped.reshape(-1, 3), distance_upper_bound=gate_mm)
    d = d.reshape(len(transforms), len(points_mm))
    hit = np.isfinite(d)
    n = hit.sum(axis=1)
    ss = np.where(hit, d, 0.0) ** 2
    rms = np.sqrt(ss.sum(axis=1) / np.maximum(n, 1))
    return n.astype(np.int64), np.asarray(rms, dtype=np.float64)


def same_pose(t_a: F64, t_b: F64, centroid_mm: F64, rotation_deg: float, translation_mm: float) -> bool:
    """True if two poses are the same hypothesis (rotation and centroid position both close)."""
    if rotation_difference_deg(t_a[:3, :3], t_b[:3, :3]) > rotation_deg:
        return False
    pa = t_a[:3, :3] @ centroid_mm + t_a[:3, 3]
    pb = t_b[:3, :3] @ centroid_mm + t_b[:3, 3]
    return float(np.linalg.norm(pa - pb)) <= translation_mm


@dataclass(frozen=True, eq=False)
class _ImagePairs:
    """The image's distance matrix and its unordered pairs sorted by length (for ``searchsorted``)."""

    d_image: F64
    sorted_mm: F64
    first: I64
    second: I64

    @classmethod
    def of(cls, image_mm: F64) -> _ImagePairs:
        d_image = pairwise_distances(image_mm)
        iu, ju = np.triu_indices(len(image_mm), 1)
        pair_d = d_image[iu, ju]
        order = np.argsort(pair_d)
        return cls(d_image, pair_d[order], iu[order].astype(np.int64), ju[order].astype(np.int64))


def consistent_image_triples(
    triple: tuple[int, int, int], d_robot: F64, pairs: _ImagePairs, pair_tol_mm: float
) -> I64:
    """(K, 3) image index triples (i, j, k) whose three distances match robot triple (a, b, c).

    |ij| matches |ab| (found by ``searchsorted``, both orders of each pair), then |ik| must match
    |ac| and |jk| must match |bc|, each within ``pair_tol_mm``.
    """
    a, b, c = triple
    lo = int(np.searchsorted(pairs.sorted_mm, d_robot[a, b] - pair_tol_mm, side="left"))
    hi = int(np.searchsorted(pairs.sorted_mm, d_robot[a, b] + pair_tol_mm, side="right"))
    if hi <= lo:
        return np.empty((0, 3), dtype=np.int64)
    ia = np.concatenate([pairs.first[lo:hi], pairs.second[lo:hi]])
    ib = np.concatenate([pairs.second[lo:hi], pairs.first[lo:hi]])
    ok = (np.abs(pairs.d_image[ia] - d_robot[a, c]) < pair_tol_mm) & (
        np.abs(pairs.d_image[ib] - d_robot[b, c]) < pair_tol_mm
    )
    p_idx, k_idx = np.nonzero(ok)
    return np.stack([ia[p_idx], ib[p_idx], k_idx], axis=1).astype(np.int64)


def score_triple_poses(
    robot_mm: F64,
    image_mm: F64,
    triple: tuple[int, int, int],
    image_triples: I64,
    tree: cKDTree,
    *,
    gate_mm: float,
    n_probes: int,
    max_scored: int,
) -> tuple[F64, I64, F64]:
    """Poses of one robot triple fitted to each image triple, scored and ranked best first.

    More than ``max_scored`` poses are first pre-filtered on ``n_probes`` far-apart robot spheres
    outside the triple.  Returns (transforms (H, 4, 4), inlier counts (H,), inlier RMS mm (H,)),
    ranked by count then RMS, without poses below :data:`MIN_HYPOTHESIS_INLIERS` inliers.
    """
    a, b, c = triple
    transforms = fit_rigid_batch(robot_mm[[a, b, c]], image_mm[image_triples])
    probe_order = farthest_point_order(robot_mm, start=a, count=n_probes + 3)
    probes = [int(p) for p in probe_order if p not in (a, b, c)][:n_probes]
    if len(transforms) > max_scored and probes:
        hits, _ = _count_inliers(transforms, robot_mm[probes], tree, gate_mm)
        transforms = transforms[np.argsort(-hits, kind="stable")[:max_scored]]
    n_in, rms = _count_inliers(transforms, robot_mm, tree, gate_mm)
    rank = np.lexsort((rms, -n_in))
    rank = rank[n_in[rank] >= MIN_HYPOTHESIS_INLIERS]
    return transforms[rank], n_in[rank], rms[rank]


class PoseClusters:
    """Distinct poses found so far: a pose close to a cluster (rotation within ``rotation_deg``
    and robot centroid within ``translation_mm``) adds its base triple to that cluster's support."""

    def __init__(self, centroid_mm: F64, rotation_deg: float, translation_mm: float) -> None:
        self._centroid = centroid_mm
        self._cos_min = float(np.cos(np.radians(rotation_deg)))
        self._translation_mm = translation_mm
        self.transforms = np.empty((0, 4, 4))
        self._positions = np.empty((0, 3))  # where each cluster maps the robot centroid
        self.n_inliers: list[int] = []
        self.rms_mm: list[float] = []
        self.triples: list[set[int]] = []

    def add(self, t: F64, n_inliers: int, rms_mm: float, triple_index: int) -> None:
        pos = t[:3, :3] @ self._centroid + t[:3, 3]
        if len(self.transforms):
            # cos of the angle between rotations: (trace(R_k Rᵀ) − 1) / 2
            cos = (np.einsum("kij,ij->k", self.transforms[:, :3, :3], t[:3, :3]) - 1.0) / 2.0
            near = (cos >= self._cos_min) & (
                np.linalg.norm(self._positions - pos, axis=1) <= self._translation_mm
            )
            hit = np.flatnonzero(near)
            if len(hit):
                self.triples[int(hit[0])].add(triple_index)
                return
        self.transforms = np.concatenate([self.transforms, t[None]])
        self._positions = np.concatenate([self._positions, pos[None]])
        self.n_inliers.append(int(n_inliers))
        self.rms_mm.append(float(rms_mm))
        self.triples.append({triple_index})

    def ranked(self) -> list[int]:
        """Cluster indices, most inliers first, then lowest RMS."""
        return sorted(
            range(len(self.n_inliers)), key=lambda i: (self.n_inliers[i], -self.rms_mm[i]), reverse=True
        )

    def best_support(self) -> int:
        """Base triples that produced the best cluster (0 if none)."""
        ranked = self.ranked()
        return len(self.triples[ranked[0]]) if ranked else 0


@dataclass(frozen=True)
class _TripleSearch:
    """The base-triple search of :func:`find_hypotheses` from one side (robot → image, or swapped)."""

    pair_tol_mm: float
    gate_mm: float
    max_base_triples: int
    min_agreeing: int
    n_probes: int
    max_scored: int

    def run(
        self,
        src_mm: F64,
        dst_mm: F64,
        dst_tree: cKDTree,
        add: Callable[[F64, int, float, int], None],
    ) -> list[tuple[int, int, int]]:
        """Base triples of ``src`` matched to ``dst``; every scored pose (dst_from_src) goes to
        ``add(pose, inliers, rms, triple index)``.  Stops once ``min_agreeing`` triples agree on the
        best pose (tracked here, for poses of this side)."""
        d_src = pairwise_distances(src_mm)
        pairs = _ImagePairs.of(dst_mm)
        triples = choose_base_triples(src_mm, d_src, pairs.sorted_mm, self.pair_tol_mm, self.max_base_triples)
        local = PoseClusters(
            src_mm.mean(axis=0), DEFAULT_DISTINCT_ROTATION_DEG, DEFAULT_DISTINCT_TRANSLATION_MM
        )
        for t_idx, triple in enumerate(triples):
            dst_triples = consistent_image_triples(triple, d_src, pairs, self.pair_tol_mm)
            if len(dst_triples) == 0:
                continue
            transforms, n_in, rms = score_triple_poses(
                src_mm,
                dst_mm,
                triple,
                dst_triples,
                dst_tree,
                gate_mm=self.gate_mm,
                n_probes=self.n_probes,
                max_scored=self.max_scored,
            )
            for t, n_t, rms_t in zip(transforms, n_in, rms, strict=True):
                add(t, int(n_t), float(rms_t), t_idx)
                local.add(t, int(n_t), float(rms_t), t_idx)
            if local.best_support() >= self.min_agreeing:
                log.debug(
                    "correspondence: best pose confirmed by %d base triples after %d",
                    local.best_support(),
                    t_idx + 1,
                )
                break
        return triples


def find_hypotheses(
    robot_mm: F64,
    image_mm: F64,
    *,
    pair_tol_mm: float,
    gate_mm: float,
    max_base_triples: int = 12,
    min_agreeing: int = 2,
    distinct_rotation_deg: float = DEFAULT_DISTINCT_ROTATION_DEG,
    distinct_translation_mm: float = DEFAULT_DISTINCT_TRANSLATION_MM,
    max_hypotheses: int = DEFAULT_MAX_HYPOTHESES,
    n_probes: int = DEFAULT_N_PROBES,
    max_scored: int = DEFAULT_MAX_SCORED,
    tree: cKDTree | None = None,
) -> list[Hypothesis]:
    """Distinct candidate poses ``image_from_robot``, best first.

    Parameters
    ----------
    robot_mm : ndarray, shape (N, 3), float64
        Labelled sphere centres, robot frame, mm.
    image_mm : ndarray, shape (M, 3), float64
        Unordered detections, image (LPS) frame, mm.
    pair_tol_mm : float
        Two distances agree when they differ by less than this (mm).
    gate_mm : float
        A robot sphere mapped by a hypothesis is an inlier when a detection
        lies within this distance (mm).
    max_base_triples, min_agreeing : int
        Search at most this many base triples; stop early once the best pose
        has been produced by ``min_agreeing`` of them.
    distinct_rotation_deg, distinct_translation_mm : float
        Hypotheses closer than both are merged.
    max_hypotheses : int
        Distinct hypotheses returned at most.

    Returns
    -------
    list of Hypothesis
        Sorted by inlier count (descending) then RMS; empty if no consistent
        triple exists.  Each pose has det R = +1.
    """
    if len(robot_mm) < 3 or len(image_mm) < 3:
        return []
    if tree is None:
        tree = cKDTree(image_mm)
    search = _TripleSearch(pair_tol_mm, gate_mm, max_base_triples, min_agreeing, n_probes, max_scored)
    clusters = PoseClusters(robot_mm.mean(axis=0), distinct_rotation_deg, distinct_translation_mm)
    triples = search.run(robot_mm, image_mm, tree, clusters.add)
    best = clusters.n_inliers[clusters.ranked()[0]] if clusters.n_inliers else 0
    if best < min(len(image_mm), len(robot_mm)):
        # Not every detection explained (part of the phantom outside the image, or no robot triple
        # fully imaged): base triples from the image side, whose points are all in the image.
        robot_tree = cKDTree(robot_mm)
        offset = len(triples)

        def add_inverted(t_robot_from_image: F64, n_img: int, rms_img: float, t_idx: int) -> None:
            t = np.asarray(np.linalg.inv(t_robot_from_image), dtype=np.float64)
            n_r, rms_r = _count_inliers(t[None], robot_mm, tree, gate_mm)
            if int(n_r[0]) >= MIN_HYPOTHESIS_INLIERS:
                clusters.add(t, int(n_r[0]), float(rms_r[0]), offset + t_idx)

        image_triples = search.run(image_mm, robot_mm, robot_tree, add_inverted)
        log.debug("correspondence: %d image-side base triples searched", len(image_triples))
        triples = triples + [(-1, -1, -1)] * len(image_triples)
    return [
        Hypothesis(
            image_from_robot=clusters.transforms[i].copy(),
            n_inliers=clusters.n_inliers[i],
            rms_mm=clusters.rms_mm[i],
            support=len(clusters.triples[i]),
            base_triples=tuple(triples[k] for k in sorted(clusters.triples[i]) if triples[k][0] >= 0),
        )
        for i in clusters.ranked()[:max_hypotheses]
    ]


EXHAUSTIVE_ROTATION_BIN: Final = 0.1
"""Rotation-matrix entries are binned at this step to drop duplicate 3-point poses before scoring
(5° of rotation moves an entry by up to sin 5° ≈ 0.09; pose noise ≈ 0.1° moves it by ≈ 0.002, so a
pose found from many triples falls into one or two bins; a split only costs one more scored pose)."""

EXHAUSTIVE_POSITION_BIN_MM: Final = 1.0
"""Where a pose lands the robot centroid is binned at this step (pose noise ≪ 1 mm ≪ 15 mm pitch)."""


def _ordered_triples(n: int) -> I64:
    """(n·(n−1)·(n−2), 3) every ordered triple of distinct indices below ``n``."""
    a, b, c = (g.ravel() for g in np.indices((n, n, n)))
    ok = (a != b) & (a != c) & (b != c)
    return np.stack([a[ok], b[ok], c[ok]], axis=1).astype(np.int64)


def exhaustive_runner_ups(
    robot_mm: F64,
    image_mm: F64,
    best_image_from_robot: F64,
    *,
    pair_tol_mm: float,
    gate_mm: float,
    distinct_rotation_deg: float = DEFAULT_DISTINCT_ROTATION_DEG,
    distinct_translation_mm: float = DEFAULT_DISTINCT_TRANSLATION_MM,
    max_hypotheses: int = DEFAULT_MAX_HYPOTHESES,
    tree: cKDTree | None = None,
) -> list[Hypothesis]:
    """Every pose distinct from ``best_image_from_robot`` that maps a robot triple onto an image triple.

    Unlike :func:`find_hypotheses` (a few base triples, early stop: enough to *find* the best pose),
    this proves there is no close runner-up: every unordered image triple (i, j, k) is paired with
    every ordered robot triple (a, b, c) whose three side lengths agree within ``pair_tol_mm``
    (|ab|↔|ij| by ``searchsorted`` on the sorted robot |ab|, then |ac|↔|ik| and |bc|↔|jk| as boolean
    masks), each pair gives a proper rigid pose (:func:`registration.matching.rigid.fit_rigid_batch`),
    duplicates are binned away (:data:`EXHAUSTIVE_ROTATION_BIN`, :data:`EXHAUSTIVE_POSITION_BIN_MM`),
    and the rest are counted at ``gate_mm`` (robot spheres within the gate of a detection).  Poses
    the same as the best (rotation within ``distinct_rotation_deg`` and the robot centroid within
    ``distinct_translation_mm``) are dropped; the others are merged into distinct poses.

    Cost grows as C(M, 3) image triples: meant for subsets (the caller bounds M).

    Returns
    -------
    list of Hypothesis
        Distinct runner-up poses, most inliers first then lowest RMS; at most ``max_hypotheses``.
    """
    n, m = len(robot_mm), len(image_mm)
    if n < 3 or m < 3:
        return []
    if tree is None:
        tree = cKDTree(image_mm)
    robot_triples, image_triples = _congruent_triple_pairs(robot_mm, image_mm, pair_tol_mm)
    if len(robot_triples) == 0:
        return []
    transforms = fit_rigid_batch(robot_mm[robot_triples], image_mm[image_triples])
    centroid = robot_mm.mean(axis=0)
    transforms, positions = _distinct_from_best(
        transforms, centroid, best_image_from_robot, distinct_rotation_deg, distinct_translation_mm
    )
    if len(transforms) == 0:
        return []
    # count every pose before binning: two poses of one bin can differ by a sphere at the gate,
    # and the bin must keep the one that explains the most (else the runner-up is understated)
    n_in, rms = _count_inliers(transforms, robot_mm, tree, gate_mm)
    order = np.lexsort((rms, -n_in))
    transforms, positions, n_in, rms = transforms[order], positions[order], n_in[order], rms[order]
    rank = _best_of_each_bin(transforms, positions)
    rank = rank[n_in[rank] >= MIN_HYPOTHESIS_INLIERS]
    clusters = PoseClusters(centroid, distinct_rotation_deg, distinct_translation_mm)
    for k in rank:
        clusters.add(transforms[k], int(n_in[k]), float(rms[k]), 0)
        if len(clusters.n_inliers) >= max_hypotheses:
            break
    log.debug(
        "correspondence: exhaustive runner-up search, %d image × robot triple pairs, %d distinct poses",
        len(robot_triples),
        len(clusters.n_inliers),
    )
    return [
        Hypothesis(
            image_from_robot=clusters.transforms[i].copy(),
            n_inliers=clusters.n_inliers[i],
            rms_mm=clusters.rms_mm[i],
            support=len(clusters.triples[i]),
        )
        for i in clusters.ranked()
    ]


def _congruent_triple_pairs(robot_mm: F64, image_mm: F64, pair_tol_mm: float) -> tuple[I64, I64]:
    """Every (ordered robot triple, unordered image triple) whose three sides agree within
    ``pair_tol_mm``: two ``(k, 3)`` index arrays, row for row (|ab|↔|ij| by ``searchsorted`` on the
    sorted robot |ab|, then |ac|↔|ik| and |bc|↔|jk| as boolean masks)."""
    n, m = len(robot_mm), len(image_mm)
    d_r = pairwise_distances(robot_mm)
    d_i = pairwise_distances(image_mm)
    abc = _ordered_triples(n)
    r_ab = d_r[abc[:, 0], abc[:, 1]]
    by_ab = np.argsort(r_ab, kind="stable")
    r_ab_sorted = r_ab[by_ab]
    ijk = np.array(list(itertools.combinations(range(m), 3)), dtype=np.int64)
    i_ij = d_i[ijk[:, 0], ijk[:, 1]]
    lo = np.searchsorted(r_ab_sorted, i_ij - pair_tol_mm, side="left")
    hi = np.searchsorted(r_ab_sorted, i_ij + pair_tol_mm, side="right")
    counts = hi - lo
    total = int(counts.sum())
    if total == 0:
        return np.empty((0, 3), dtype=np.int64), np.empty((0, 3), dtype=np.int64)
    img_rep = np.repeat(np.arange(len(ijk)), counts)
    starts = np.repeat(lo - (np.cumsum(counts) - counts), counts)
    rob = by_ab[np.arange(total) + starts]
    ok = (np.abs(d_r[abc[rob, 0], abc[rob, 2]] - d_i[ijk[img_rep, 0], ijk[img_rep, 2]]) < pair_tol_mm) & (
        np.abs(d_r[abc[rob, 1], abc[rob, 2]] - d_i[ijk[img_rep, 1], ijk[img_rep, 2]]) < pair_tol_mm
    )
    return abc[rob[ok]], ijk[img_rep[ok]]


def _distinct_from_best(
    transforms: F64,
    centroid: F64,
    best_image_from_robot: F64,
    distinct_rotation_deg: float,
    distinct_translation_mm: float,
) -> tuple[F64, F64]:
    """The poses not the same as the best (:func:`same_pose`, vectorised: the cosine of the rotation
    angle between them, and the distance the robot centroid lands apart), with where each puts the
    centroid."""
    positions = np.einsum("hij,j->hi", transforms[:, :3, :3], centroid) + transforms[:, :3, 3]
    best_pos = best_image_from_robot[:3, :3] @ centroid + best_image_from_robot[:3, 3]
    cos = (np.einsum("kij,ij->k", transforms[:, :3, :3], best_image_from_robot[:3, :3]) - 1.0) / 2.0
    distinct = (cos < float(np.cos(np.radians(distinct_rotation_deg)))) | (
        np.linalg.norm(positions - best_pos, axis=1) > distinct_translation_mm
    )
    return transforms[distinct], positions[distinct]


def _best_of_each_bin(transforms: F64, positions: F64) -> I64:
    """Indices of the first pose of each bin (:data:`EXHAUSTIVE_ROTATION_BIN`,
    :data:`EXHAUSTIVE_POSITION_BIN_MM`), in input order: on poses sorted most inliers first then
    lowest RMS, the best of each bin in that order."""
    keys = np.concatenate(
        [
            np.round(transforms[:, :3, :3].reshape(-1, 9) / EXHAUSTIVE_ROTATION_BIN),
            np.round(positions / EXHAUSTIVE_POSITION_BIN_MM),
        ],
        axis=1,
    )
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first).astype(np.int64)
