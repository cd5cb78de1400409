"""Defects of two aligned visits matched, and each crack's growth.

Each visit's crack mask is split into its connected components (as ``detect`` measures
them). A BEFORE component and an AFTER component are the same defect when BEFORE's
skeleton, carried into AFTER by the alignment, runs within ``tolerance_px`` of AFTER's
component; the matches form groups (a crack detected in pieces on one visit and whole on
the other is one defect), as are pieces of one visit within ``join_px`` of each other.
Defects shorter than the unchanged tolerance on both visits are left out: no growth could
be told on them. Lengths are skeleton lengths counted only over the surface both
images show, BEFORE's converted to AFTER's pixels by the alignment's local scale, so a
crack cut by the other image's border does not grow for that.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.exposure import match_histograms
from skimage.morphology import skeletonize

from processing.detection.defects import Components, skeleton_length
from processing.history.align import Alignment
from processing.history.confirm import gray_float, still_there


@dataclass(frozen=True)
class ChangeParams:
    """When two detections are one defect, and when a length differs."""

    tolerance_px: float = 4.0  # plus the alignment's residual
    # pieces of one visit this close are one defect (a crack detected with gaps)
    join_px: float = 8.0
    unchanged_px: float = 20.0  # |growth| below max(this, unchanged_fraction x length)
    unchanged_fraction: float = 0.10
    weak_support: float = 0.5  # of a defect's length along the other visit's weak evidence


@dataclass(frozen=True)
class Change:
    """One defect of either visit: its status and lengths (AFTER's pixels)."""

    id: int
    status: str  # new, gone, unchanged, grown
    bbox_after: tuple[int, int, int, int] | None  # x, y, w, h
    bbox_before: tuple[int, int, int, int] | None
    length_before_px: float | None
    length_after_px: float | None

    @property
    def growth_px(self) -> float:
        """AFTER's length minus BEFORE's (a missing one counted as 0)."""
        return (self.length_after_px or 0.0) - (self.length_before_px or 0.0)


@dataclass(frozen=True)
class CrackEvidence:
    """A visit's crack mask, and the weaker evidence (a lower threshold) that keeps a crack
    seen on the other visit from counting as new or gone where this one shows it faintly."""

    mask: NDArray[np.bool_]
    weak: NDArray[np.bool_]


def crack_evidence(image: NDArray[np.uint8], method: str = "learned") -> CrackEvidence:
    """The crack mask of ``image`` by ``method`` and, for the network, its pixels above a quarter of
    the model's threshold (other methods have no graded output: their mask is the weak one)."""
    from processing.detection import detect_cracks, to_gray
    from processing.detection.learned import crack_probability, load_model

    if method != "learned":
        mask = detect_cracks(image, method=method)  # type: ignore[arg-type]
        return CrackEvidence(mask, mask)
    p = crack_probability(to_gray(image))
    t = load_model().threshold
    return CrackEvidence(p > t, p > 0.25 * t)


def lit_like(image: NDArray[np.uint8], reference: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """``image`` with each channel's grey levels mapped to ``reference``'s distribution
    (histogram matching): the detector then sees both visits under one lighting."""
    if image.ndim != reference.ndim:
        return image
    axis = -1 if image.ndim == 3 else None
    matched = match_histograms(image, reference, channel_axis=axis)
    return np.clip(np.rint(matched), 0, 255).astype(np.uint8)


def _transform(H: NDArray[np.float64], xy: NDArray[np.float64]) -> NDArray[np.float64]:
    if not len(xy):
        return xy.reshape(0, 2)
    moved = cv2.perspectiveTransform(xy.reshape(-1, 1, 2).astype(np.float64), H)
    return np.asarray(moved, np.float64).reshape(-1, 2)


def _disc(radius_px: float) -> NDArray[np.uint8]:
    """A disc-shaped structuring element of (at least 1 px) ``radius_px``."""
    r = max(1, int(np.ceil(radius_px)))
    return np.asarray(cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))


def _carried(
    mask: NDArray[np.bool_], H: NDArray[np.float64], shape: tuple[int, ...]
) -> NDArray[np.int64]:
    """(N, 2) whole-pixel (x, y) where ``H`` carries ``mask``'s pixels, those landing inside
    an image of ``shape`` only."""
    ys, xs = np.nonzero(mask)
    q = np.round(_transform(H, np.stack([xs, ys], 1).astype(np.float64))).astype(np.int64)
    h, w = shape[:2]
    return q[(q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)]


def common_mask(
    H_to_other: NDArray[np.float64], shape: tuple[int, ...], other_shape: tuple[int, ...]
) -> NDArray[np.bool_]:
    """(H, W) pixels of an image of ``shape`` that ``H_to_other`` maps inside the other."""
    h, w = shape[:2]
    oh, ow = other_shape[:2]
    ones = np.ones((oh, ow), np.uint8)
    # WARP_INVERSE_MAP: the matrix maps this image's pixels to the other's
    warped = cv2.warpPerspective(
        ones, H_to_other, (w, h), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    )
    return np.asarray(warped, bool)


def _local_scale(H: NDArray[np.float64], at: NDArray[np.float64]) -> float:
    """Length scale of ``H`` at point ``at``: √|det J|."""
    p = _transform(H, np.array([at, at + (1.0, 0.0), at + (0.0, 1.0)]))
    J = np.stack([p[1] - p[0], p[2] - p[0]], axis=1)
    return float(np.sqrt(abs(np.linalg.det(J))))


@dataclass
class _Pieces:
    """One visit's defect components: labels, bounding boxes, skeletons."""

    comps: Components
    ids: list[int]
    skeletons: dict[int, NDArray[np.bool_]]  # full-size skeleton per component

    @classmethod
    def of(cls, mask: NDArray[np.bool_]) -> _Pieces:
        comps = Components.of(mask)
        ids = np.flatnonzero(comps.keep).tolist()
        skel = skeletonize(mask)
        return cls(comps, ids, {i: skel & (comps.labels == i) for i in ids})

    def bbox(self, members: list[int]) -> tuple[int, int, int, int]:
        boxes = np.array([self.comps.stats[i][:4] for i in members])
        x0, y0 = boxes[:, 0].min(), boxes[:, 1].min()
        x1, y1 = (boxes[:, 0] + boxes[:, 2]).max(), (boxes[:, 1] + boxes[:, 3]).max()
        return int(x0), int(y0), int(x1 - x0), int(y1 - y0)

    def line(self, members: list[int]) -> NDArray[np.bool_]:
        return np.any([self.skeletons[i] for i in members], axis=0)

    def length(self, members: list[int], common: NDArray[np.bool_]) -> float:
        return float(sum(skeleton_length(self.skeletons[i] & common) for i in members))


@dataclass(frozen=True)
class _Views:
    """Both images' grey levels, each also carried into the other's frame."""

    before: NDArray[np.float32]
    after: NDArray[np.float32]
    after_in_before: NDArray[np.float32]
    before_in_after: NDArray[np.float32]

    @classmethod
    def of(
        cls, images: tuple[NDArray[np.uint8], NDArray[np.uint8]], H_a2b: NDArray[np.float64]
    ) -> _Views:
        gb, ga = gray_float(images[0]), gray_float(images[1])
        (hb, wb), (ha, wa) = gb.shape, ga.shape
        # H_a2b maps AFTER's pixels to BEFORE's: forward for AFTER → BEFORE's frame,
        # as the inverse map for BEFORE → AFTER's frame
        a_in_b = cv2.warpPerspective(ga, H_a2b, (wb, hb), flags=cv2.INTER_LINEAR)
        b_in_a = cv2.warpPerspective(
            gb, H_a2b, (wa, ha), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        )
        return cls(gb, ga, np.asarray(a_in_b, np.float32), np.asarray(b_in_a, np.float32))


def _joins(pieces: _Pieces, offset: int, join_px: float) -> list[tuple[int, int]]:
    """Graph edges between pieces of one visit within ``join_px`` of each other."""
    kernel = _disc(join_px / 2)
    labels = pieces.comps.labels * np.isin(pieces.comps.labels, pieces.ids)
    # the largest and the smallest label within reach of each pixel: where they differ,
    # two pieces come within join_px of each other
    high = cv2.dilate(labels.astype(np.float32), kernel).astype(np.int64)
    background = float(2**24)
    low = cv2.erode(np.where(labels > 0, labels, background).astype(np.float32), kernel)
    low = low.astype(np.int64)
    close = (high > 0) & (low < high)
    index = {label: k for k, label in enumerate(pieces.ids)}
    pairs = {
        (index[int(a)], index[int(b)])
        for a, b in zip(low[close], high[close])
        if int(a) in index and int(b) in index
    }
    return [(offset + a, offset + b) for a, b in pairs]


def _links(
    before: _Pieces, after: _Pieces, H_b2a: NDArray[np.float64], tol_px: float
) -> list[tuple[int, int]]:
    """(BEFORE index, AFTER index) pairs whose components meet under the alignment."""
    kernel = _disc(tol_px)
    kept = np.isin(after.comps.labels, after.ids)
    # a dilated label image: where two meet, the larger label wins
    near = cv2.dilate((after.comps.labels * kept).astype(np.float32), kernel).astype(np.int32)
    hits = cv2.dilate(kept.astype(np.uint8), kernel).astype(bool)
    links = set()
    for bi, j in enumerate(before.ids):
        q = _carried(before.skeletons[j], H_b2a, near.shape)
        q = q[hits[q[:, 1], q[:, 0]]]
        for label in np.unique(near[q[:, 1], q[:, 0]]):
            if label in after.ids:
                links.add((bi, after.ids.index(int(label))))
    return sorted(links)


def match_defects(
    before_mask: NDArray[np.bool_],
    after_mask: NDArray[np.bool_],
    after_to_before: NDArray[np.float64],
    residual_px: float = 0.0,
    params: ChangeParams = ChangeParams(),
    before_weak: NDArray[np.bool_] | None = None,
    after_weak: NDArray[np.bool_] | None = None,
    images: tuple[NDArray[np.uint8], NDArray[np.uint8]] | None = None,
) -> list[Change]:
    """The changes between BEFORE's and AFTER's crack masks ((H, W) each) aligned by the
    AFTER → BEFORE homography; defects on no surface both images show are left out. With
    a visit's weak evidence (``before_weak``, ``after_weak``), a defect of the other visit
    that runs along it for at least ``weak_support`` of its length is not new or gone but
    seen faintly: unchanged. With the two ``images`` (AFTER lit like BEFORE), a new or gone
    defect along whose line the other image is as dark is unchanged too
    (:mod:`.confirm`)."""
    H_a2b = np.asarray(after_to_before, np.float64)
    H_b2a = np.asarray(np.linalg.inv(H_a2b), np.float64)
    before, after = _Pieces.of(before_mask), _Pieces.of(after_mask)
    common_b = common_mask(H_b2a, before_mask.shape, after_mask.shape)
    common_a = common_mask(H_a2b, after_mask.shape, before_mask.shape)
    links = _links(before, after, H_b2a, params.tolerance_px + residual_px)
    views = _Views.of(images, H_a2b) if images is not None else None
    weak = (before_weak, after_weak)
    nb, na = len(before.ids), len(after.ids)
    edges = [(b, nb + a) for b, a in links]
    edges += _joins(before, 0, params.join_px) + _joins(after, nb, params.join_px)
    rows = [a for a, _ in edges]
    cols = [b for _, b in edges]
    graph = coo_matrix((np.ones(len(edges)), (rows, cols)), shape=(nb + na, nb + na))
    _, group = connected_components(graph, directed=False)
    changes: list[Change] = []
    for g in np.unique(group):
        members = np.flatnonzero(group == g)
        bs = [before.ids[m] for m in members if m < nb]
        as_ = [after.ids[m - nb] for m in members if m >= nb]
        change = _change(
            len(changes) + 1, bs, as_, before, after, common_b, common_a, H_b2a, params
        )
        if change is None:
            continue
        if (
            change.status == "grown"
            and views is not None
            and _grown_part_was_there(
                before, bs, after, as_, H_b2a, params.tolerance_px + residual_px, views
            )
        ):
            change = replace(change, status="unchanged", length_before_px=change.length_after_px)
        if change.status in ("new", "gone") and _still_seen(
            change, bs, as_, before, after, H_a2b, H_b2a, residual_px, params, weak, views
        ):
            kept = change.length_before_px or change.length_after_px
            change = replace(
                change, status="unchanged", length_before_px=kept, length_after_px=kept
            )
        changes.append(change)
    return changes


def _grown_part_was_there(
    before: _Pieces,
    bs: list[int],
    after: _Pieces,
    as_: list[int],
    H_b2a: NDArray[np.float64],
    tol_px: float,
    views: _Views,
) -> bool:
    """Whether BEFORE's image is as dark along the part of AFTER's crack that BEFORE's
    detection lacks (then the crack was as long, its end missed by the detector)."""
    line = after.line(as_)
    q = _carried(before.line(bs), H_b2a, line.shape)
    old = np.zeros(line.shape, np.uint8)
    old[q[:, 1], q[:, 0]] = 1
    added = line & ~cv2.dilate(old, _disc(tol_px)).astype(bool)
    return bool(added.any()) and still_there(added, views.after, views.before_in_after)


def _still_seen(
    change: Change,
    bs: list[int],
    as_: list[int],
    before: _Pieces,
    after: _Pieces,
    H_a2b: NDArray[np.float64],
    H_b2a: NDArray[np.float64],
    residual_px: float,
    params: ChangeParams,
    weak: tuple[NDArray[np.bool_] | None, NDArray[np.bool_] | None],
    views: _Views | None,
) -> bool:
    """Whether a new or gone defect shows on the other visit after all: along its weak
    evidence, or as a line as dark in the other image."""
    tol = params.tolerance_px + residual_px
    if change.status == "gone":
        pieces, members, H, other_weak = before, bs, H_b2a, weak[1]
    else:
        pieces, members, H, other_weak = after, as_, H_a2b, weak[0]
    if (
        other_weak is not None
        and _support(pieces, members, H, other_weak, tol) >= params.weak_support
    ):
        return True
    if views is None:
        return False
    line = pieces.line(members)
    if change.status == "gone":
        return still_there(line, views.before, views.after_in_before)
    return still_there(line, views.after, views.before_in_after)


def _support(
    pieces: _Pieces,
    members: list[int],
    H_to_other: NDArray[np.float64],
    other_weak: NDArray[np.bool_],
    tol_px: float,
) -> float:
    """Fraction of the members' skeleton pixels that land near the other visit's weak
    evidence (those landing outside the other image not counted)."""
    near = cv2.dilate(other_weak.astype(np.uint8), _disc(tol_px)).astype(bool)
    q = _carried(pieces.line(members), H_to_other, other_weak.shape)
    if not len(q):
        return 0.0
    return float(near[q[:, 1], q[:, 0]].mean())


def _change(
    cid: int,
    bs: list[int],
    as_: list[int],
    before: _Pieces,
    after: _Pieces,
    common_b: NDArray[np.bool_],
    common_a: NDArray[np.bool_],
    H_b2a: NDArray[np.float64],
    params: ChangeParams,
) -> Change | None:
    len_b = len_a = None
    if bs:
        box = before.bbox(bs)
        centre = np.array([box[0] + box[2] / 2, box[1] + box[3] / 2])
        len_b = before.length(bs, common_b) * _local_scale(H_b2a, centre)
    if as_:
        len_a = after.length(as_, common_a)
    if max(len_b or 0.0, len_a or 0.0) < params.unchanged_px:
        return None  # on no surface both images show, or too short to tell a growth
    if not bs:
        status = "new"
    elif not as_:
        status = "gone"
    else:
        growth = (len_a or 0.0) - (len_b or 0.0)
        limit = max(params.unchanged_px, params.unchanged_fraction * (len_a or 0.0))
        status = "grown" if growth > limit else "unchanged"
    return Change(
        cid,
        status,
        after.bbox(as_) if as_ else None,
        before.bbox(bs) if bs else None,
        None if len_b is None else round(len_b, 2),
        None if len_a is None else round(len_a, 2),
    )


def compare_visits(
    before: NDArray[np.uint8],
    after: NDArray[np.uint8],
    alignment: Alignment,
    evidence: Callable[[NDArray[np.uint8]], CrackEvidence] = crack_evidence,
    params: ChangeParams = ChangeParams(),
) -> list[Change]:
    """The changes between two aligned visits' images: AFTER relit like BEFORE, cracks found
    in both by ``evidence`` (the network by default), matched and confirmed on the images."""
    lit = lit_like(after, before)
    seen_before, seen_after = evidence(before), evidence(lit)
    return match_defects(
        seen_before.mask,
        seen_after.mask,
        alignment.after_to_before,
        alignment.residual_px,
        params,
        before_weak=seen_before.weak,
        after_weak=seen_after.weak,
        images=(before, lit),
    )
