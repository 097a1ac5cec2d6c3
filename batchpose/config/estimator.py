"""The whole estimator's config (:class:`EstimatorConfig`: the decisions that span the steps, then one section
per step) and :func:`validate`: every field's own rules, then the few rules that tie two fields together."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from batchpose.config.plane import PlaneConfig
from batchpose.config.rules import check_fields, knob
from batchpose.config.sections import (
    CarryConfig,
    DepthConfig,
    FeatureConfig,
    FineConfig,
    GncConfig,
    MatchConfig,
    MeshConfig,
    RefineConfig,
    RegionConfig,
    RenderConfig,
    TrackConfig,
    WeightsConfig,
)
from batchpose.errors import ConfigError


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything that decides a pose, one section per stage."""

    method: str = knob("gnc_pose", choices=("gnc_pose", "tp_ub"))
    """"gnc_pose" or "tp_ub" (template upper bound: needs ground truth, evaluation only)."""
    min_matches: int = knob(6, ge=4, note="PnP")
    """Fewer 2D-3D pairs than this: status too_few_matches."""
    min_distinct_inliers: int = knob(4, ge=0)
    """A pose whose inliers lie on fewer distinct frame pixels than this (to the pixel) is pnp_failed: a frame
    keypoint matched to several templates is one point, and fewer than 4 points leave a pose undetermined
    (any pose through them fits them). 0: no check (the ``paper`` pipeline)."""
    max_pose_spread: float = knob(0.5, ge=0)
    """A full estimate whose inliers pin it only loosely is low_confidence: when 1-px noise on the inliers'
    image positions would move the object's surface points by more than this fraction of its diameter (RMS,
    from the pose's least-squares covariance: :func:`batchpose.method.gnc_pnp.pose_spread`). Inliers along
    one line (a pen seen side-on) fit a nearer, more tilted object as well as a farther, flatter one. Applies
    to every SIFT pose (first pass, retries, the alternatives check), not to tracked poses or the plane
    search's (the table pins those). 0: no check (the ``paper`` pipeline and the ablations)."""
    confidence_inliers: float = knob(15.0, gt=0)
    """Confidence = (1 - exp(-n_inliers / this)) * exp(-median_residual_px / confidence_residual_px)."""
    confidence_residual_px: float = knob(4.0, gt=0)
    """See ``confidence_inliers``."""
    min_confidence: float = knob(0.3, ge=0, le=1)
    """A full estimate less confident than this is not reported as a pose: status low_confidence (the pose stays
    in ``poses.parquet`` for inspection, not in ``poses.csv`` or the MCAP's scene). Such poses rest on a
    handful of pairs: on benchmarks/heldout.py (seeds 0-2, 384 pairs) no right pose (ADD-S < 0.1 d) was
    below 0.39, and 36 of the 74 wrong ones reported ok were below 0.3 (all but one over 10 cm off, so
    out of the AUC anyway); on ycbv_dev 2 of 4 (0.3 and 2.7 m off). ``depth.enabled``: a low-confidence
    pose the depth image aligns is reported (the depth vouches for it). 0: report every pose."""
    verify_below: float = knob(0.5, ge=0, le=1)
    """A full estimate less confident than this (a weak one: 6-10 inliers) is checked against the frame: the
    mesh rendered at the pose must correlate (Lab) with the frame over its pixels no other reported pose
    hides at least ``verify_min_match``, or its status is low_confidence. On benchmarks/tabletop.py and
    heldout.py 30 of 31 weak SIFT poses were wrong or of absent objects (texture match -0.2-0.23 for the
    absent ones), the right one matched 0.65. One whose mesh shows under 30 px in the frame (past
    ``render.zfar_m``, beside the image) cannot be checked and is low_confidence too. 0: no check."""
    min_verification: float = knob(0.5, ge=0, lt=1)
    """Every untracked pose (first pass, retry, search) is rendered and compared with the frame: its outline
    against the frame's edges, its gradients and its colours, combined into one score, the estimated
    probability that the pose is on the object (``verification`` in poses.parquet;
    :mod:`batchpose.method.score`). An ok pose scoring under this is low_confidence. 0: no score (the
    paper's pipelines)."""
    retry_rejected: bool = True
    """An ok pose the verification score (``min_verification``) rejects gives its object the retries a
    missed object gets: matched again against its second library (``render.retry_shading``), then from
    keypoints at the lower contrast threshold (``features.retry_*``). The frame's keypoints are detected
    again, once a frame that has such a pose; a new pose is kept only when it passes the same score. False:
    a rejected pose stays low_confidence. ycbv_dev, every frame afresh: 158 -> 160 ok of 160, 87.9 / 68.6 ->
    89.1 / 69.5 mean ADD-S / ADD AUC; held-out single frames 687 -> 689 ok, 80.0 -> 80.2; the tracked
    default's poses unchanged (reports/ACCURACY.md, "Template shading")."""
    verified_tracks: bool = True
    """Where the mesh at a pose fails the texture match that lets a track start, survive a refresh or carry a
    pose into the next frame (``track.min_match``), let it pass when the verification score does
    (``min_verification``): a shiny or reflective surface (a metal lid) renders in colours the frame does not
    show while its outline and gradients match. False, or ``min_verification`` 0: the texture match alone."""
    track_verification: float = knob(0.8, ge=0, le=1)
    """A track starts only from a pose whose verification score is at least this (where one is computed,
    ``min_verification`` > 0, and the depth step does not judge the frame): a track carries its first pose
    through up to ``track.chunk_frames`` frames, so it needs surer ground than one reported pose. 0.8 is the
    score above which 99 % of the poses were right on the frames the score was fitted on
    (``benchmarks/verification.py``). 0: any ok pose starts one."""
    verify_min_match: float = knob(0.35, ge=-1, le=1)
    """See ``verify_below`` (the depth and plane searches keep what they find by the same threshold)."""
    planar_spread: float = knob(0.05, ge=0, lt=1)
    """A full estimate whose inliers' model points lie on one plane (their smallest spread under this fraction
    of the middle one: one face of a box, a can's lid) is checked for the planar ambiguity: a plane a small
    object shows from afar fits two poses about equally well, tilted either way about the line of sight
    (IPPE gives both; the wrong one turns a box 30-100 degrees about its visible face). When the other pose
    reprojects the inliers about as well (``planar_residual_ratio``), the mesh is rendered at both and, over
    the pixels where the two renders differ, compared with the frame by colour (Lab correlation, as
    ``verify_below``) and by edges (Sobel gradients); the other pose is kept when it fits better by both
    (``planar_mismatch_ratio``). 0: no check (the ``paper`` pipeline)."""
    alternatives: int = knob(2, ge=0)
    """A full estimate that refined several hypotheses (``refine.hypotheses``) also checks up to this many of
    the others against the pose it chose: those whose guided score is at least ``alternatives_score`` of the
    best one's, with at least that fraction of the pose's own inliers, and that differ from the pose (over 5
    degrees or 0.1 diameters apart), best first, and the best refined hypothesis when the template pairs'
    pose won over it by inlier count (but by less than that fraction). Each is rendered beside
    the pose and compared with the frame where the two renders differ, by colour and by edges, as
    ``planar_spread``'s check is (with ``planar_mismatch_ratio``); it replaces the pose when both prefer it.
    Guided scores of a right and a wrong pose of a small, weakly textured object are often within a few
    pairs. 0: no check (the ``paper`` pipeline)."""
    alternatives_score: float = knob(0.5, gt=0, le=1)
    """See ``alternatives``."""
    checks_score_margin: float = knob(0.02, ge=0, le=1)
    """The other pose of ``alternatives``' and ``planar_spread``'s checks also replaces the pose when, each
    rendered whole, its verification score (:mod:`batchpose.method.score`, as ``min_verification``'s) is
    higher by at least this, though colour and edges where the two differ do not both prefer it: a box's
    printed face seen from afar fits two poses (one shows it from below, the bottom where the frame shows the
    lid), and the outline tells them apart where the printed face cannot. 1: colour and edges alone."""
    planar_residual_ratio: float = knob(2.0, ge=1)
    """See ``planar_spread``: the other pose's median inlier residual may be at most this many times the
    pose's own (taken as at least 0.5 px)."""
    planar_mismatch_ratio: float = knob(1.1, ge=1)
    """See ``planar_spread``: the other pose replaces the pose when, by colour and by edges each, its mismatch
    (1 - match) is at most the pose's own divided by this. Either cue alone errs (colour where an occluder
    covers the object, edges on clutter); on held-out seeds 3 and 4 and tabletop seed 0 the two agreed on
    all 9 cases reached, which neither did alone (reports/ACCURACY.md at 8fba8e3, "Session 15")."""
    min_object_px: float = 12.0
    """A pose at which the object's diameter would span fewer pixels than this is implausible: the frame
    could not show it (status pnp_failed, and never used to place the fine pass's box)."""
    max_object_image_fraction: float = 3.0
    """... or more than this many times the image's longer side (or the object is behind the camera)."""
    support_px: float = 2.0
    """Poses from different passes and refinement hypotheses are compared by their support: the pairs they
    reproject within this many pixels (0: GNC's inlier count, which a wrong pose gathering loose pairs at
    5-8 px can win)."""
    strong_inliers: int = knob(40, ge=0)
    """A whole-frame pass with at least this many inliers (and a plausible pose) has found the object: no
    fine pass, no locator, and the refinement refines that pose only, one round (no per-template
    hypotheses, no turned copies). Such a full estimate costs about half as much at equal accuracy. 40
    against 60: ycbv_dev 88.3 / 72.8 against 88.2 / 72.6 mean ADD-S / ADD AUC, held-out seeds 3-4 (8
    frames an object) 87.4 / 86.9 and 86.4 / 85.9 against 87.4 / 86.9 and 86.5 / 86.0, at a third fewer
    refinement renders and half the fine passes on unrelated frames (reports/BENCHMARKS.md). 0: never."""
    max_image_side_px: int = knob(0, ge=160, off="full resolution")
    """Frames whose longer side exceeds this are estimated at that size (resized, the camera scaled with
    them; templates rendered for the scaled camera); poses, inlier points and residuals are reported for
    the full frame. 0: full resolution. An HD camera's frames cost several times a 640x480 frame's time and
    memory (reports/BENCHMARKS.md at 8fba8e3, "Session 32"); the pixel thresholds here were set on 640x480 frames.
    Fewer pixels also mean fewer keypoints on a small object: measure on your own frames."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    weights: WeightsConfig = field(default_factory=WeightsConfig)
    gnc: GncConfig = field(default_factory=GncConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    fine: FineConfig = field(default_factory=FineConfig)
    track: TrackConfig = field(default_factory=TrackConfig)
    carry: CarryConfig = field(default_factory=CarryConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    plane: PlaneConfig = field(default_factory=PlaneConfig)
    region: RegionConfig = field(default_factory=RegionConfig)


def _retry_below_contrast(conf: EstimatorConfig) -> str | None:
    # 0 (off) passes: the fields' own rules keep the retry's threshold >= 0 and the first one's > 0.
    fc = conf.features
    if fc.retry_contrast_threshold < fc.contrast_threshold:
        return None
    return (
        f"features.retry_contrast_threshold must be 0 (off) or below features.contrast_threshold "
        f"({fc.contrast_threshold:g}), got {fc.retry_contrast_threshold:g}"
    )


def _znear_below_zfar(conf: EstimatorConfig) -> str | None:
    r = conf.render
    return None if r.znear_m < r.zfar_m else f"render.znear_m must be positive and below render.zfar_m, got {r.znear_m}"


def _gate_narrows(conf: EstimatorConfig) -> str | None:
    dc = conf.depth
    if dc.gate_final_m <= dc.gate_m:
        return None
    return f"depth.gate_final_m must be positive and at most gate_m, got {dc.gate_final_m}"


def _max_points_cover_min_pixels(conf: EstimatorConfig) -> str | None:
    dc = conf.depth
    return None if dc.max_points >= dc.min_pixels else f"depth.max_points must be >= min_pixels, got {dc.max_points}"


CROSS_FIELD_CHECKS: tuple[Callable[[EstimatorConfig], str | None], ...] = (
    _retry_below_contrast,
    _znear_below_zfar,
    _gate_narrows,
    _max_points_cover_min_pixels,
)
"""Rules that tie two fields together, run after every field has passed its own (:func:`knob`) rules."""


def validate(conf: EstimatorConfig, where: str = "pipeline") -> EstimatorConfig:
    """Check every field's choices and bounds, then the cross-field rules; raise ConfigError naming the field."""
    check_fields(conf, where)
    for check in CROSS_FIELD_CHECKS:
        problem = check(conf)
        if problem:
            raise ConfigError(f"{where}: {problem}")
    return conf
