"""Pipeline configuration: frozen dataclasses whose defaults are SPEC.md's values.

A pipeline YAML (``pipelines/*.yaml``) sets any subset of these fields; unknown keys are an error.
``--set section.field=value`` overrides one field (the value is parsed as YAML).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from batchpose.errors import ConfigError


@dataclass(frozen=True)
class MeshConfig:
    """How meshes are loaded."""

    units: str = "auto"
    """"m", "mm", or "auto": a bounding-box diagonal > ``mm_diagonal_threshold`` means millimetres."""
    on_millimetres: str = "convert"
    """What to do with a millimetre mesh under ``units: auto``: "convert" (scale 1/1000, warn) or "refuse"."""
    mm_diagonal_threshold: float = 5.0
    """Bounding-box diagonal (in file units) above which a mesh is taken to be in millimetres (SPEC §1)."""
    max_texture_px: int = 2048
    """Textures larger than this (longer side) are downscaled on load: templates and refinement renders are
    at most a few hundred pixels across, and a 4096² texture costs 64 MB of GL memory per object."""


@dataclass(frozen=True)
class RenderConfig:
    """Template views (SPEC §1)."""

    view_preset: str = "sphere"
    """"sphere": Fibonacci sampling of the whole view sphere; "paper": one azimuth ring at a fixed height."""
    n_views: int = 160
    """Viewpoints on the sphere (``sphere`` preset)."""
    min_elevation_deg: float = -90.0
    """Lowest camera elevation above the model's x-y plane (``sphere`` preset); -90 covers the whole sphere."""
    paper_azimuth_step_deg: float = 10.0
    """Azimuth step over [-180, 180) (``paper`` preset)."""
    paper_height_m: float = 1.0
    """Camera height above the model origin (``paper`` preset); the distance is ``distances_m[0]``."""
    distances_m: tuple[float, ...] = ()
    """Camera distances in metres; empty: chosen per object from ``image_fractions``."""
    image_fractions: tuple[float, ...] = (0.5, 0.25)
    """With automatic distances: the object's diameter spans this fraction of the image's shorter side."""
    width: int = 0
    """Template image width; 0: the data set camera's width (or 640)."""
    height: int = 0
    """Template image height; 0: the data set camera's height (or 480)."""
    shading: str = "flat"
    """"flat" (albedo only, matches texture) or "lit" (a headlight plus ambient light)."""
    znear_m: float = 0.01
    zfar_m: float = 20.0


@dataclass(frozen=True)
class FeatureConfig:
    """SIFT features, for templates and queries alike."""

    n_features: int = 0
    """Keep at most this many keypoints per image (0: all)."""
    contrast_threshold: float = 0.02
    """SIFT's contrast threshold: half OpenCV's 0.04, for more keypoints on dim, blurred or small objects
    (the ``paper`` and ``fast`` pipelines keep 0.04; reports/ACCURACY.md has both)."""
    retry_contrast_threshold: float = 0.01
    """When a full estimate finds no pose (not found, or below ``min_confidence``) or only a weak one (below
    ``verify_below``), detect the frame's SIFT keypoints again with this lower contrast threshold and
    estimate that object once more (its fine pass inside the object's box too), keeping the new pose if it
    is ok and more confident (0: no retry; the ``paper`` and ``fast`` pipelines). Costs a second detection
    in frames where an object is missing or weak; confidently found objects are never affected. Held-out
    sets (benchmarks/heldout.py) seeds 0 / 1 / 2 / 3: 82.4 / 80.3 / 83.7 / 78.8 without the retry, 88.4 /
    84.3 / 84.8 / 82.7 mean ADD-S AUC with it (85.4 / 85.3 / 85.7 / 80.8 when the fine pass kept the default
    contrast); ycbv_dev unchanged (reports/ACCURACY.md, "Session 13" and "Session 14")."""
    retry_sigma: float = 1.2
    """A second retry, for the objects the first one (``retry_contrast_threshold``) did not find either, or
    found only weakly: keypoints detected again at ``retry_contrast_threshold`` with SIFT's base blur at
    this σ instead of ``sigma``, which keeps finer print (0: no second retry; no effect without the first).
    Kept under the first retry's rule: ok and more confident. Held-out seeds 3-14 (2,304 pairs, paired):
    mean ADD-S / ADD AUC 85.3 / 84.0 -> 86.3 / 85.0, no seed lower, 21 more right poses and 13 more wrong
    ones reported ok; fresh seeds 15-16: 83.0 / 81.7 -> 83.8 / 82.7; ycbv_dev and the scale logs unchanged;
    ~15 % more compute per pair on the held-out frames, none on a tracked log (reports/ACCURACY.md,
    "Session 25")."""
    edge_threshold: float = 10.0
    sigma: float = 1.6
    root_sift: bool = True
    """Use RootSIFT (Arandjelović & Zisserman 2012: L1-normalised, square-rooted) descriptors, compared by
    Euclidean distance = Hellinger kernel; the ``paper`` pipeline keeps SIFT's (reports/ACCURACY.md,
    "Session 11")."""
    crop_padding_px: int = 16
    """Templates: run SIFT only on the object's bounding box plus this margin (saves time, same features)."""


@dataclass(frozen=True)
class MatchConfig:
    """2D-3D correspondences (SPEC §2)."""

    direction: str = "template_to_query"
    """"template_to_query": ratio test from each template keypoint into the frame's keypoints;
    "query_to_template": from each frame keypoint into the object's template descriptors."""
    ratio: float = 0.75
    """Lowe's ratio-test threshold."""
    distinct_3d_m: float = 0.01
    """query_to_template: the ratio is taken against the nearest neighbour whose 3D point is farther than
    this from the best match's (a second view of the same surface point is not a rival)."""
    top_k_templates: int = 3
    """Keep the pairs of the k templates with the most surviving matches."""
    prefilter_views: int = 32
    """template_to_query: first vote for views with each frame keypoint's nearest template descriptor and
    test only the keypoints of the ``prefilter_views`` most-voted views (0: test every view). On ycbv_dev
    32 views halve the time per pair with no accuracy change beyond run-to-run noise."""
    prefilter_ratio: float = 0.9
    """Loose ratio test a frame keypoint must pass to vote for a view (see ``prefilter_views``)."""
    first_views: int = 8
    """Whole-frame pass with ``prefilter_views``: test the keypoints of this many most-voted views first and
    the other views' only when those do not give a strong pose (``strong_inliers``); the pairs are then
    exactly those of all ``prefilter_views`` views. A strong object is matched ~4x faster (0: off)."""
    flann_trees: int = 4
    flann_checks: int = 32
    roi: str = "none"
    """"none": whole image; "gt_box": oracle box from ground truth (evaluation only, never default)."""
    roi_margin_px: int = 24


@dataclass(frozen=True)
class WeightsConfig:
    """Geometry-aware weights (SPEC §3)."""

    mode: str = "correspondences"
    """"correspondences": voxel support over this frame's 3D points; "model": support over all template
    keypoints of the library; "none": every weight is 1 (the no_geom_weights ablation)."""
    voxel_m: float = 0.005
    w_min: float = 0.2


@dataclass(frozen=True)
class GncConfig:
    """RANSAC initialisation, GNC-PnP with dual-filter inlier selection, final LM (SPEC §4)."""

    enabled: bool = True
    """False: RANSAC-PnP + LM only (the ransac_only ablation)."""
    ransac_reproj_px: float = 8.0
    ransac_iterations: int = 1000
    ransac_confidence: float = 0.999
    residual: str = "pixels"
    """"pixels": r = ||proj - x||; "squared": r = ||proj - x||^2."""
    kappa: float = 5.0
    epsilon: float = 1e-6
    mu0_from: str = "ransac_inliers"
    """Median for mu0 over "all" correspondences (the paper) or over the RANSAC inliers."""
    tau_gnc: float = 0.5
    tau_geom: float = 0.25
    min_inliers: int = 6
    gamma: float = 0.5
    mu_final_px: float = 0.5
    max_iterations: int = 50
    final_lm: bool = True


@dataclass(frozen=True)
class RefineConfig:
    """Render-and-match refinement (batchpose's addition; see :mod:`batchpose.method.refine`)."""

    enabled: bool = True
    """Refine every pose by matching the frame against the mesh rendered at that pose."""
    iterations: int = 2
    """Rounds of render -> SIFT -> guided matching -> PnP."""
    radius_px: float = 12.0
    """A rendered keypoint matches only frame keypoints within this many pixels of it."""
    ratio: float = 0.85
    """Ratio test among the frame keypoints within the radius."""
    mu_final_px: float = 1.5
    """GNC's final scale for the guided pairs (their keypoint noise is real-image noise, not 0.5 px)."""
    gnc: bool = True
    """Solve the guided pairs with GNC (as ``gnc.enabled``); false: RANSAC-PnP + LM over all its inliers."""
    hypotheses: int = 4
    """Also refine poses solved from each of the best templates alone, up to this many hypotheses in all,
    and keep the one with the most guided inliers."""
    flips: bool = True
    """Also try the best hypothesis turned 180 degrees about each of the mesh's principal axes (the poses a
    texture-symmetric object is most often confused with); keep whichever has the most guided inliers."""
    polish: bool = False
    """Finish every full estimate with a dense render-and-compare alignment (:meth:`PoseEstimator._polish`):
    corners of the frame on the mesh rendered at the pose are found again, by normalised cross-correlation
    within ``polish_search_px``, in that render, and the pose is solved again by Levenberg-Marquardt from
    them (the tracker's ``track.render_every`` step), ``polish_rounds`` times. It sharpens the distance
    along the line of sight where the mesh and the calibration match the images exactly: unseen held-out
    frames (rendered meshes, seeds 3-14) 85.3 / 84.0 -> 86.1 / 85.3 mean ADD-S / ADD AUC, median ADD 1.5 ->
    0.9 mm. On ycbv_dev's real frames it moves poses farther still from the ground truth and the depth
    sensor (90.5 / 79.1 -> 88.9 / 76.5, the tracked frames following it too; reports/ACCURACY.md
    "Session 23"), so it is off by default. Costs a render and about 200 patch searches a round, for full
    estimates only."""
    polish_rounds: int = 3
    """Render, search and solve rounds of ``polish``; each starts from the last round's pose."""
    polish_search_px: int = 4
    """How far from where the pose projects it a corner's rendered patch is looked for."""


@dataclass(frozen=True)
class FineConfig:
    """Coarse-to-fine matching (batchpose's addition): after the whole-frame pass, find the object's box
    and match again inside it, upsampled, against every template view."""

    enabled: bool = True
    upsample: float = 2.0
    """Scale the crop by this factor before SIFT (small, blurred objects give few keypoints at 1x)."""
    max_side_px: int = 1024
    """Lower the upsampling factor so the scaled crop's longer side stays within this."""
    margin: float = 0.15
    """Grow the box by this fraction of its size on every side (the coarse pose may be off)."""
    margin_px: int = 16
    """... plus this many pixels."""
    prefilter_views: int = 32
    """Views tested inside the box, chosen by the crop's keypoints' votes as in ``match.prefilter_views``
    (0: every view, which costs about twice the time for no measured gain on ycbv_dev)."""
    cluster_radius_px: float = 48.0
    """Without a coarse pose: the box is that of the matched keypoints near the densest of them, within
    twice this radius."""
    locate: bool = True
    """When the best pose so far (the whole frame's, or the coarse box's fine pass's) is weak, also run
    the fine pass where the frame's keypoints vote the object to be
    (:func:`batchpose.method.correspondences.locate`: each match predicts the object's centre, size and in-plane
    rotation from its keypoint's scale and angle); the pass with the most support wins. A small object in
    clutter often loses the whole-frame pass to a handful of chance matches elsewhere."""
    locate_below: float = 0.5
    """"Weak": no pose, an implausible one, or confidence below this."""
    locate_votes: int = 4
    """Fewest agreeing keypoints for a location."""
    locate_ratio: float = 0.8
    """Ratio test (against the nearest descriptor of another 3D point) for a frame keypoint to vote."""
    locate_peaks: int = 1
    """Locations searched: the fullest vote cell, then the fullest among the votes it leaves, ... (one fine
    pass each, skipping a box already searched). 2 measured no gain on benchmarks/heldout.py (68.2/65.5
    against 68.0/65.6, 16 frames/object, seed 1) for 25 % more estimate time."""
    locate_pairs: bool = True
    """Add the agreeing votes' 2D-3D pairs to the pairs matched in the located box."""
    locate_angle_deg: float = 30.0
    """Width of the in-plane rotation bins (0: do not vote on rotation). Chance matches agree on a
    place less often when they must also agree on the object's in-plane rotation."""


@dataclass(frozen=True)
class TrackConfig:
    """Frame-to-frame tracking (batchpose's addition; see :mod:`batchpose.method.track`): a confident pose is
    followed into the next frames with optical flow and PnP instead of being estimated afresh."""

    enabled: bool = True
    max_gap_s: float = 0.25
    """Follow a pose only into a later frame of the same scene and camera at most this many seconds on."""
    min_confidence: float = 0.5
    """Start a track only from a full estimate at least this confident."""
    redetect_every: int = 0
    """Estimate afresh after this many tracked frames (0: only when the track is lost or the worker task
    ends, i.e. at least every ``chunk_frames`` frames)."""
    points: int = 200
    """Corners seeded on the object at the keyframe."""
    quality: float = 0.01
    """Shi-Tomasi quality level of a seeded corner (fraction of the strongest corner's score)."""
    min_distance_px: float = 5.0
    """Seeded corners are at least this far apart."""
    min_ncc: float = 0.5
    """A corner is seeded only where the frame correlates with the mesh rendered at the pose at least this
    much (normalised cross-correlation of the patches): corners on an occluder are not the object."""
    ncc_radius_px: int = 5
    """Half-side of the patches compared for ``min_ncc``."""
    min_points: int = 12
    """A track is lost with fewer surviving points than this ..."""
    min_fraction: float = 0.5
    """... or than this fraction of its seeded points."""
    anchor: bool = True
    """Also flow each point straight from the keyframe (started where frame-to-frame flow ended), so that
    flow errors do not add up over a track."""
    anchor_px: float = 2.0
    """Use the keyframe flow where it lands within this many pixels of the frame-to-frame flow."""
    occlusion_margin_px: int = 10
    """When two tracked objects overlap in the image, drop each one's points that lie within this many
    pixels of the other's image region (its convex hull projected at its last pose) and are farther from the
    camera than the other's nearest point (-1: keep them). Lucas-Kanade follows texture, so a point that an
    object moving in front covers is dragged along with it, and with it the pose. The margin covers a
    frame's motion and the flow window. Dropped points count as never seeded, so hiding part of an object
    does not by itself end its track."""
    render_every: int = 0
    """Every this many tracked frames, pull the points back onto the mesh: find each point's patch of the
    mesh rendered at the tracked pose in the frame (NCC within ``render_search_px``) and solve again
    (0: never)."""
    refresh_every: int = 32
    """After this many tracked frames (or when fewer than ``reseed_fraction`` of the points survive), make
    the tracked frame a new keyframe instead of estimating afresh: pull the pose onto the mesh rendered there
    (as ``render_every``; the track ends if too few points are found) and seed new corners (0: never).
    Costs a render and a seeding (~3 % of a full estimate) and removes the flow's drift, which is what lets
    ``chunk_frames`` be 64."""
    reseed_fraction: float = 0.75
    """See ``refresh_every``."""
    refresh_turn_deg: float = 20.0
    """Refresh also when the camera has moved this far around the object since the keyframe (the angle
    between the two directions from the object to the camera; 0: never for that reason): the points
    seeded on the sides it showed then do not cover the sides it shows now."""
    min_match: float = 0.35
    """A track starts, and survives a refresh, only where the mesh rendered at its pose looks like the
    frame over its whole silhouette (texture match, as ``verify_min_match``, over the pixels no object
    found in front hides); else the object is estimated afresh in the next frame, or at once at a
    refresh (0: no check). A wrong but confident full estimate would otherwise be followed for dozens of
    frames; and a track's points all lie on what was visible at its keyframe: when the object turns that
    part edge-on they can stay aligned while the pose turns the wrong way, which the pull onto the mesh,
    looking only near each point, cannot see."""
    render_search_px: int = 3
    """How far from its tracked position a point's rendered patch is looked for."""
    fb_max_px: float = 1.0
    """A point survives a frame when optical flow back from its new position lands this close to the old."""
    reproj_px: float = 3.0
    """... and its reprojection error at the tracked pose is at most this."""
    window_px: int = 15
    """Lucas-Kanade window side."""
    levels: int = 3
    """Lucas-Kanade pyramid levels above the full image."""
    lost_full_every: int = 4
    """While an object stays lost (its estimates start no track) in consecutive frames, only every this
    many-th of them gets the full estimate; the others get a quick one: the whole-frame pass against the
    ``match.first_views`` most-voted views only, and one refinement of its pose (~3x cheaper). An object
    counts as lost until a track of it lives this many frames. An occluded or absent object
    then costs a third of the time; one that reappears is found up to this many frames later where only
    the fine pass or locator finds it. 1: always the full estimate."""
    hidden_above: float = 0.6
    """A lost object whose last confident pose is at least this fraction covered (its projected convex
    hull) by tracked objects in front of it is estimated only every ``lost_full_every``-th frame (see
    ``hidden_quick``); in the frames between, where it would get a quick estimate, its status is
    ``hidden``, naming what hides it. It is estimated in every frame again as soon as less of it is
    covered. Estimates of a mostly hidden object are slow (whole-frame SIFT and matching even for a quick
    one) and often wrong (1: never skip)."""
    hidden_quick: bool = True
    """Make those every-``lost_full_every``-th estimates of a mostly hidden object quick ones (see
    ``lost_full_every``), so that a second object in the frame costs at most 0.3x the decode + SIFT floor
    even where one hides the other. False gives them the full estimate: on the two-object benchmark log
    (reports/BENCHMARKS.md, session 18) the further object's cost rises from +0.2x to +0.47x the floor, and
    the fine pass finds a mostly hidden object in a few more frames (ADD < 0.1 d 95.4 -> 95.8 % of the log's
    pairs)."""
    hidden_retry: bool = False
    """Give those full estimates of a mostly hidden object ``features.retry_contrast_threshold``'s retry
    too. Off: the object was not found because it is hidden, not for want of contrast, and the retry (SIFT
    at the lower threshold, then a second full estimate) more than doubles the estimate's time."""
    chunk_frames: int = 64
    """Frames per worker task while tracking. A track never crosses tasks, so results do not depend on
    ``--jobs``; each task starts with a full estimate per object. Two-object benchmark log (800 frames,
    reports/BENCHMARKS.md): 32 frames without refreshes 93.8 ADD AUC at +0.72x the floor per further
    object; 64 with ``refresh_every`` 32: 94.9 at +0.47x; 128: tracks drift (ADD < 0.1 d 93 -> 88.5 %)
    and a short log splits into too few tasks to share between workers."""


@dataclass(frozen=True)
class DepthConfig:
    """Optional use of a depth image registered to the colour image (batchpose's addition; see
    :mod:`batchpose.method.depth`). The RGB estimate is unchanged; each pose it finds is then aligned to the sensor's
    depth (robust point-to-plane ICP on the object's pixels), which fixes the weak axis of a monocular pose,
    the distance along the viewing ray. Frames without a depth image keep their RGB poses."""

    enabled: bool = False
    level: int = 2
    """Work on every ``level``-th pixel of the depth image (and of the renders): ~2x cheaper at 2 than at 1,
    with ample points for a 6-DoF fit."""
    iterations: int = 8
    """ICP iterations (the object's pixels are chosen anew at each)."""
    gate_m: float = 0.03
    """A pixel is the object's when its sensor depth is within this of the mesh rendered at the pose: at the
    first iteration ..."""
    gate_final_m: float = 0.01
    """... narrowing linearly to this at the last."""
    min_pixels: int = 50
    """Fewer object pixels with a sensor reading than this: the pose is left as the RGB estimate gave it."""
    max_points: int = 1500
    """Depth pixels on and around the object used (evenly subsampled)."""
    damping: float = 0.05
    """Levenberg damping of the ICP step (relative): directions the depth cannot see, such as a can's turn
    about its axis or a box's on its flat face, stay where the RGB estimate put them (at 0.001 the ICP
    turned right box poses 23-28 degrees on the held-out set; the depth search aligns with 0.001)."""
    max_shift: float = 0.25
    """An alignment that moves the object's centre by more than this fraction of its diameter, or turns it by
    more than ``max_turn_deg``, is not used: the RGB pose and the depth disagree about which surface it is."""
    max_turn_deg: float = 20.0
    """See ``max_shift``."""
    max_see_through: float = 0.5
    """With more than this fraction of the object's silhouette showing sensor depth farther than the object
    (the camera sees past where the pose puts it), the pose contradicts the depth: status pnp_failed.
    Nearer readings are occluders and do not count (1: never fail a pose)."""
    min_agree: float = 0.1
    """With less than this fraction of the silhouette's readings within a quarter of the object's diameter of
    the rendered surface, the pose contradicts the depth too: the sensor sees the object nowhere there, e.g.
    a pose far behind the objects in front of it (0: never fail a pose)."""
    search: bool = False
    """Look for an object the RGB estimate did not find (or whose pose the depth contradicts) by colour
    and depth (:mod:`batchpose.method.depth_search`, ~3–10 s an object). A pose found this way has reason
    "found by the depth search" and confidence at most 0.5."""
    search_view_step: int = 4
    """Use every this-many-th library view (at the nearest distance) as a silhouette."""
    search_angles: int = 12
    """In-plane turns of each silhouette."""
    search_hypotheses: int = 5
    """Places aligned to the depth (each also turned 180 degrees about the mesh's three principal axes)."""
    search_polish: int = 3
    """The best-fitting this-many distinct hypotheses whose texture lines up at all are turned about their
    principal axes (20, 10, 5 degrees) and aligned again while that fits better (0: keep the best as
    aligned); the best that passes the checks below is kept."""
    search_min_visible: float = 0.4
    """Keep a found pose only if the sensor sees at least this fraction of its silhouette at its surface ..."""
    search_max_see_through: float = 0.1
    """... sees past at most this fraction ..."""
    search_min_colour: float = 1.2
    """... the seen pixels have the object's colours: mean log-odds of their colours under the object's
    colour histogram against the frame's outside the silhouette at least this (1.2: 3.3 times likelier) ..."""
    search_min_match: float = 0.35
    """... and in the right places: the mesh rendered at the pose correlates (normalised, in Lab) with the
    frame over the seen pixels at least this well. A flat face laid onto a wall of similar colours fits the
    depth and the histogram but not the texture's layout (-0.02 there); objects found right on ycbv_dev and
    the held-out set 0.47-0.9, absent objects kept on ycbv_dev's synthetic frames 0.30 (a tomato soup can
    on a tuna can, a large marker) and 0.52 (the pudding box on the gelatin box, both Jell-O boxes)."""


@dataclass(frozen=True)
class PlaneConfig:
    """Looking for an object SIFT missed on the surface the found objects rest on (batchpose's addition; see
    :mod:`batchpose.method.plane`). Runs only for an object without a pose in a frame where at least
    ``min_objects`` others were found confidently and rest on one plane; not where ``depth.search`` has a depth
    image to search with."""

    enabled: bool = True
    min_objects: int = 2
    """Fewest confidently found objects that define a support plane ..."""
    min_confidence: float = 0.5
    """... each at least this confident ..."""
    max_spread_m: float = 0.03
    """... whose lowest points along the plane's normal are at most this far apart (poses on real frames are
    1-3 % off in distance; ycbv_dev's video 0001: 11-13 mm)."""
    plane_candidates: int = 64
    """Normals tried: each found object's this many largest convex-hull faces, turned downwards."""
    min_stable: float = 0.02
    """Resting faces of the object looked for: its stable poses (trimesh) at least this probable. A bottle
    upright is one of its less probable ones (0.04 for the mustard bottle)."""
    angles: int = 12
    """Turns about the plane's normal tried for each resting face."""
    min_span_px: float = 12.0
    """Places where the object would span fewer pixels are not searched."""
    starts: int = 4
    """Best distinct placements of the coarse search refined."""
    colour_weight: float = 0.2
    """Weight of the mean colour log-odds against the texture correlation in the refinement's score."""
    min_visible: float = 0.3
    """A placement is kept if at least this fraction of its silhouette is not hidden by a found object ..."""
    min_colour: float = 0.5
    """... those pixels' mean colour log-odds (the object's histogram against the frame's outside the found
    objects) is at least this ..."""
    min_match: float = 0.35
    """... the mesh rendered there correlates (Lab) with the frame over them at least this well ..."""
    min_contrast: float = 1.5
    """... and it stands out: their mean colour log-odds exceeds that of the 4-px ring around the silhouette
    (found objects left out) by at least this. On ycbv_dev the mustard bottle found 3.0-3.9; objects the
    frame does not show, placed where the colours and texture fit best (a white marker on the white table,
    a can on the mustard bottle), 0.3-1.0."""
    edge_weight: float = 0.5
    """Weight of the edge score (:attr:`batchpose.method.plane.Placed.edge`: how closely the frame's edges follow
    the placed silhouette's outline) in the refinement's score. 0: edges are not looked at while refining.
    It also aligns wrong placements with whatever edges are near: alone it took the poses of objects the
    frames do not show from 2 to 7 (tabletop seeds 0-1), with ``min_edge`` 0.4 from 4 to 10 (seeds 0-5);
    hence ``min_edge``'s 0.6."""
    min_edge: float = 0.6
    """A placement is kept only if its edge score is at least this (0: not checked; nor where the frame has
    no edges near the placement at all). At their true poses the tabletop's markers and bleach cleansers have
    0.67-0.97 of their outline within 1.5 px of an edge; with ``edge_weight`` 0.5 the
    placements of absent objects that passed every other check scored 0.40-0.62 (tabletop seeds 0-2; this
    value was chosen from them). Tabletop seeds 0-3 against 0 / 0: right 20 -> 23, wrong 2 -> 1, absent
    objects placed 2 -> 1 (reports/ACCURACY.md, "Session 27")."""
    edge_confirms: float = 0.75
    """A finely refined placement that fails one of the two colour checks (``min_colour``, ``min_contrast``)
    is kept if its edge score is at least this: a pale bottle on a white table has the table's colours, a thin
    marker a pixel aside has its own pixels in the contrast's ring. 0: off. Chosen between the edges of the
    truth (0.67-0.97) and of absent objects' placements (90 % under 0.41); with the border fix of session 28,
    tabletop seeds 0-7 replayed: right 39 -> 52, wrong 4 -> 1, absent objects placed 2 -> 2 (reports/ACCURACY.md,
    "Session 28")."""
    reface: bool = True
    """Also refine, at each coarsely refined start's place, the two best of the object's other resting faces
    with its long axis kept (a bottle lying on its other side, a box on its back): the silhouette barely
    differs, the texture does. Tabletop seeds 1-4, the plane search replayed with and without it: +0.71,
    0.00, +0.84 and -0.10 pairs of credit (a power drill and a bleach cleanser found); ycbv_dev's mustard
    bottle moves 0.3-2.6 mm. It doubles the search's time (tabletop: 2.9 -> 5.1 s a search; reports/ACCURACY.md,
    "Session 30"). False: the coarse search's faces only."""


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything that decides a pose, one section per stage."""

    method: str = "gnc_pose"
    """"gnc_pose" or "tp_ub" (template upper bound: needs ground truth, evaluation only)."""
    min_matches: int = 6
    """Fewer 2D-3D pairs than this: status too_few_matches."""
    confidence_inliers: float = 15.0
    """Confidence = (1 - exp(-n_inliers / this)) * exp(-median_residual_px / confidence_residual_px)."""
    confidence_residual_px: float = 4.0
    min_confidence: float = 0.3
    """A full estimate less confident than this is not reported as a pose: status low_confidence (the pose stays
    in ``poses.parquet`` for inspection, not in ``poses.csv`` or the MCAP's scene). Such poses rest on a
    handful of pairs: on benchmarks/heldout.py (seeds 0-2, 384 pairs) no right pose (ADD-S < 0.1 d) was
    below 0.39, and 36 of the 74 wrong ones reported ok were below 0.3 (all but one over 10 cm off, so
    out of the AUC anyway); on ycbv_dev 2 of 4 (0.3 and 2.7 m off). ``depth.enabled``: a low-confidence
    pose the depth image aligns is reported (the depth vouches for it). 0: report every pose."""
    verify_below: float = 0.5
    """A full estimate less confident than this (a weak one: 6-10 inliers) is checked against the frame: the
    mesh rendered at the pose must correlate (Lab) with the frame over its pixels no other reported pose
    hides at least ``verify_min_match``, or its status is low_confidence. On benchmarks/tabletop.py and
    heldout.py 30 of 31 weak SIFT poses were wrong or of absent objects (texture match -0.2-0.23 for the
    absent ones), the right one matched 0.65. One whose mesh shows under 30 px in the frame (past
    ``render.zfar_m``, beside the image) cannot be checked and is low_confidence too. 0: no check."""
    verify_min_match: float = 0.35
    """See ``verify_below`` (the depth and plane searches keep what they find by the same threshold)."""
    planar_spread: float = 0.05
    """A full estimate whose inliers' model points lie on one plane (their smallest spread under this fraction
    of the middle one: one face of a box, a can's lid) is checked for the planar ambiguity: a plane a small
    object shows from afar fits two poses about equally well, tilted either way about the line of sight
    (IPPE gives both; the wrong one turns a box 30-100 degrees about its visible face). When the other pose
    reprojects the inliers about as well (``planar_residual_ratio``), the mesh is rendered at both and, over
    the pixels where the two renders differ, compared with the frame by colour (Lab correlation, as
    ``verify_below``) and by edges (Sobel gradients); the other pose is kept when it fits better by both
    (``planar_mismatch_ratio``). 0: no check (the ``paper`` pipeline)."""
    alternatives: int = 2
    """A full estimate that refined several hypotheses (``refine.hypotheses``) also checks up to this many of
    the others against the pose it chose: those whose guided score is at least ``alternatives_score`` of the
    best one's, with at least that fraction of the pose's own inliers, and that differ from the pose (over 5
    degrees or 0.1 diameters apart), best first, and the best refined hypothesis when the template pairs'
    pose won over it by inlier count (but by less than that fraction). Each is rendered beside
    the pose and compared with the frame where the two renders differ, by colour and by edges, as
    ``planar_spread``'s check is (with ``planar_mismatch_ratio``); it replaces the pose when both prefer it.
    Guided scores of a right and a wrong pose of a small, weakly textured object are often within a few
    pairs. 0: no check (the ``paper`` pipeline)."""
    alternatives_score: float = 0.5
    """See ``alternatives``."""
    planar_residual_ratio: float = 2.0
    """See ``planar_spread``: the other pose's median inlier residual may be at most this many times the
    pose's own (taken as at least 0.5 px)."""
    planar_mismatch_ratio: float = 1.1
    """See ``planar_spread``: the other pose replaces the pose when, by colour and by edges each, its mismatch
    (1 - match) is at most the pose's own divided by this. Either cue alone errs (colour where an occluder
    covers the object, edges on clutter); on held-out seeds 3 and 4 and tabletop seed 0 the two agreed on
    all 9 cases reached, which neither did alone (reports/ACCURACY.md, "Session 15")."""
    min_object_px: float = 12.0
    """A pose at which the object's diameter would span fewer pixels than this is implausible: the frame
    could not show it (status pnp_failed, and never used to place the fine pass's box)."""
    max_object_image_fraction: float = 3.0
    """... or more than this many times the image's longer side (or the object is behind the camera)."""
    support_px: float = 2.0
    """Poses from different passes and refinement hypotheses are compared by their support: the pairs they
    reproject within this many pixels (0: GNC's inlier count, which a wrong pose gathering loose pairs at
    5-8 px can win)."""
    strong_inliers: int = 60
    """A whole-frame pass with at least this many inliers (and a plausible pose) has found the object: no
    fine pass, no locator, and the refinement refines that pose only, one round (no per-template
    hypotheses, no turned copies). Such a full estimate costs about half as much at equal accuracy
    (reports/BENCHMARKS.md). 0: never."""
    max_image_side_px: int = 0
    """Frames whose longer side exceeds this are estimated at that size (resized, the camera scaled with
    them; templates rendered for the scaled camera); poses, inlier points and residuals are reported for
    the full frame. 0: full resolution. An HD camera's frames cost several times a 640x480 frame's time and
    memory (reports/BENCHMARKS.md "Session 32"); the pixel thresholds here were set on 640x480 frames.
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
    depth: DepthConfig = field(default_factory=DepthConfig)
    plane: PlaneConfig = field(default_factory=PlaneConfig)


_CHOICES = {
    ("mesh", "units"): ("auto", "m", "mm"),
    ("mesh", "on_millimetres"): ("convert", "refuse"),
    ("render", "view_preset"): ("sphere", "paper"),
    ("render", "shading"): ("flat", "lit"),
    ("match", "direction"): ("template_to_query", "query_to_template"),
    ("match", "roi"): ("none", "gt_box"),
    ("weights", "mode"): ("correspondences", "model", "none"),
    ("gnc", "residual"): ("pixels", "squared"),
    ("gnc", "mu0_from"): ("all", "ransac_inliers"),
    ("", "method"): ("gnc_pose", "tp_ub"),
}


def _coerce(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        (inner, _) = typing.get_args(tp)
        return tuple(_coerce(v, inner, where) for v in value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def from_dict(cls: type, data: dict | None, where: str = "config", key: str = "") -> Any:
    """Build dataclass ``cls`` from a nested dict; unknown keys and wrong types raise ConfigError.

    Errors read ``WHERE: KEY: ...`` (e.g. ``pipelines/x.yaml: gnc.kappa: expected a number``); ``key`` is the
    dotted path of ``data`` inside the file (empty at the top).
    """
    data = data or {}
    at = f"{where}: {key}" if key else where
    if not isinstance(data, dict):
        raise ConfigError(f"{at}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields), key=str)
    if unknown:
        raise ConfigError(
            f"{at}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(str, unknown))} "
            f"(expected one of: {', '.join(fields)})"
        )
    kwargs = {}
    for name, value in data.items():
        tp = hints[name]
        sub = f"{key}.{name}" if key else name
        if dataclasses.is_dataclass(tp):
            kwargs[name] = from_dict(tp, value, where, sub)
        else:
            kwargs[name] = _coerce(value, tp, f"{where}: {sub}")
    obj = cls(**kwargs)
    return obj


def validate(conf: EstimatorConfig, where: str = "pipeline") -> EstimatorConfig:
    """Check enumerated fields and value ranges; raise ConfigError naming the field."""
    for (section, name), choices in _CHOICES.items():
        value = getattr(getattr(conf, section) if section else conf, name)
        if value not in choices:
            key = f"{section}.{name}" if section else name
            raise ConfigError(f"{where}: {key} = {value!r}, expected one of {', '.join(choices)}")
    if not 0 < conf.match.ratio <= 1:
        raise ConfigError(f"{where}: match.ratio must be in (0, 1], got {conf.match.ratio}")
    if conf.render.n_views < 1 or conf.match.top_k_templates < 1:
        raise ConfigError(f"{where}: render.n_views and match.top_k_templates must be >= 1")
    if conf.weights.voxel_m <= 0:
        raise ConfigError(f"{where}: weights.voxel_m must be positive, got {conf.weights.voxel_m}")
    if conf.fine.upsample < 1 or conf.fine.max_side_px < 32:
        raise ConfigError(f"{where}: fine.upsample must be >= 1 and fine.max_side_px >= 32")
    if not 0 < conf.fine.locate_ratio <= 1 or not 0 <= conf.fine.locate_angle_deg <= 180:
        raise ConfigError(f"{where}: fine.locate_ratio must be in (0, 1] and fine.locate_angle_deg in [0, 180]")
    if conf.fine.locate_peaks < 1 or conf.fine.locate_votes < 1:
        raise ConfigError(f"{where}: fine.locate_peaks and fine.locate_votes must be >= 1")
    fc = conf.features
    if not 0 <= fc.retry_contrast_threshold < fc.contrast_threshold:
        raise ConfigError(
            f"{where}: features.retry_contrast_threshold must be 0 (off) or below features.contrast_threshold "
            f"({fc.contrast_threshold:g}), got {fc.retry_contrast_threshold:g}"
        )
    if fc.retry_sigma < 0:
        raise ConfigError(f"{where}: features.retry_sigma must be 0 (off) or positive, got {fc.retry_sigma:g}")
    tc = conf.track
    for key, ok, need in (
        ("max_gap_s", tc.max_gap_s > 0, "be positive"),
        ("points", tc.points >= 1, "be >= 1"),
        ("min_points", tc.min_points >= 6, "be >= 6 (PnP)"),
        ("min_fraction", 0 <= tc.min_fraction <= 1, "be in [0, 1]"),
        ("redetect_every", tc.redetect_every >= 0, "be >= 0"),
        ("window_px", tc.window_px >= 5, "be >= 5"),
        ("min_ncc", -1 <= tc.min_ncc <= 1, "be in [-1, 1]"),
        ("ncc_radius_px", tc.ncc_radius_px >= 1, "be >= 1"),
        ("occlusion_margin_px", tc.occlusion_margin_px >= -1, "be >= -1"),
        ("render_every", tc.render_every >= 0, "be >= 0"),
        ("refresh_every", tc.refresh_every >= 0, "be >= 0"),
        ("reseed_fraction", 0 <= tc.reseed_fraction <= 1, "be in [0, 1]"),
        ("min_match", 0 <= tc.min_match < 1, "be in [0, 1)"),
        ("refresh_turn_deg", 0 <= tc.refresh_turn_deg <= 180, "be in [0, 180]"),
        ("render_search_px", tc.render_search_px >= 1, "be >= 1"),
        ("levels", tc.levels >= 0, "be >= 0"),
        ("chunk_frames", tc.chunk_frames >= 1, "be >= 1"),
        ("lost_full_every", tc.lost_full_every >= 1, "be >= 1"),
        ("hidden_above", 0 < tc.hidden_above <= 1, "be in (0, 1]"),
    ):
        if not ok:
            raise ConfigError(f"{where}: track.{key} must {need}, got {getattr(tc, key)}")
    dc = conf.depth
    for key, ok, need in (
        ("level", dc.level >= 1, "be >= 1"),
        ("iterations", dc.iterations >= 1, "be >= 1"),
        ("gate_m", dc.gate_m > 0, "be positive"),
        ("gate_final_m", 0 < dc.gate_final_m <= dc.gate_m, "be positive and at most gate_m"),
        ("min_pixels", dc.min_pixels >= 6, "be >= 6"),
        ("max_points", dc.max_points >= dc.min_pixels, "be >= min_pixels"),
        ("damping", dc.damping >= 0, "be >= 0"),
        ("max_shift", dc.max_shift > 0, "be positive"),
        ("max_turn_deg", dc.max_turn_deg > 0, "be positive"),
        ("max_see_through", 0 <= dc.max_see_through <= 1, "be in [0, 1]"),
        ("min_agree", 0 <= dc.min_agree <= 1, "be in [0, 1]"),
        ("search_view_step", dc.search_view_step >= 1, "be >= 1"),
        ("search_angles", dc.search_angles >= 1, "be >= 1"),
        ("search_hypotheses", dc.search_hypotheses >= 1, "be >= 1"),
        ("search_polish", dc.search_polish >= 0, "be >= 0"),
        ("search_min_match", -1 <= dc.search_min_match <= 1, "be in [-1, 1]"),
        ("search_min_visible", 0 <= dc.search_min_visible <= 1, "be in [0, 1]"),
        ("search_max_see_through", 0 <= dc.search_max_see_through <= 1, "be in [0, 1]"),
    ):
        if not ok:
            raise ConfigError(f"{where}: depth.{key} must {need}, got {getattr(dc, key)}")
    pc = conf.plane
    for key, ok, need in (
        ("min_objects", pc.min_objects >= 2, "be >= 2"),
        ("min_confidence", 0 <= pc.min_confidence <= 1, "be in [0, 1]"),
        ("max_spread_m", pc.max_spread_m > 0, "be positive"),
        ("plane_candidates", pc.plane_candidates >= 1, "be >= 1"),
        ("min_stable", 0 <= pc.min_stable <= 1, "be in [0, 1]"),
        ("angles", pc.angles >= 1, "be >= 1"),
        ("min_span_px", pc.min_span_px >= 1, "be >= 1"),
        ("starts", pc.starts >= 1, "be >= 1"),
        ("colour_weight", pc.colour_weight >= 0, "be >= 0"),
        ("min_visible", 0 < pc.min_visible <= 1, "be in (0, 1]"),
        ("min_match", -1 <= pc.min_match <= 1, "be in [-1, 1]"),
        ("min_contrast", pc.min_contrast >= 0, "be >= 0"),
        ("edge_weight", pc.edge_weight >= 0, "be >= 0"),
        ("min_edge", 0 <= pc.min_edge <= 1, "be in [0, 1]"),
        ("edge_confirms", 0 <= pc.edge_confirms <= 1, "be in [0, 1]"),
    ):
        if not ok:
            raise ConfigError(f"{where}: plane.{key} must {need}, got {getattr(pc, key)}")
    if not 0 <= conf.verify_below <= 1:
        raise ConfigError(f"{where}: verify_below must be in [0, 1], got {conf.verify_below}")
    if not -1 <= conf.verify_min_match <= 1:
        raise ConfigError(f"{where}: verify_min_match must be in [-1, 1], got {conf.verify_min_match}")
    if not 0 <= conf.planar_spread < 1:
        raise ConfigError(f"{where}: planar_spread must be in [0, 1), got {conf.planar_spread}")
    if conf.alternatives < 0:
        raise ConfigError(f"{where}: alternatives must be >= 0, got {conf.alternatives}")
    if not 0 < conf.alternatives_score <= 1:
        raise ConfigError(f"{where}: alternatives_score must be in (0, 1], got {conf.alternatives_score}")
    if conf.planar_residual_ratio < 1:
        raise ConfigError(f"{where}: planar_residual_ratio must be >= 1, got {conf.planar_residual_ratio}")
    if conf.planar_mismatch_ratio < 1:
        raise ConfigError(f"{where}: planar_mismatch_ratio must be >= 1, got {conf.planar_mismatch_ratio}")
    if not 0 <= conf.min_confidence <= 1:
        raise ConfigError(f"{where}: min_confidence must be in [0, 1], got {conf.min_confidence}")
    if conf.strong_inliers < 0:
        raise ConfigError(f"{where}: strong_inliers must be >= 0, got {conf.strong_inliers}")
    if conf.max_image_side_px != 0 and conf.max_image_side_px < 160:
        raise ConfigError(
            f"{where}: max_image_side_px must be 0 (full resolution) or >= 160, got {conf.max_image_side_px}"
        )
    if not 0 < conf.gnc.gamma < 1:
        raise ConfigError(f"{where}: gnc.gamma must be in (0, 1), got {conf.gnc.gamma}")
    _check_ranges(conf, where)
    return conf


def _check_ranges(conf: EstimatorConfig, where: str) -> None:
    """The numeric fields the checks above do not cover: ranges outside which a run would fail in every
    frame, loop forever or silently do nothing."""
    g, r, m, f, rf, fn = conf.gnc, conf.render, conf.match, conf.features, conf.refine, conf.fine
    for key, value, ok, need in (
        ("mesh.mm_diagonal_threshold", conf.mesh.mm_diagonal_threshold, conf.mesh.mm_diagonal_threshold > 0, "> 0"),
        ("mesh.max_texture_px", conf.mesh.max_texture_px, conf.mesh.max_texture_px >= 16, ">= 16"),
        ("render.width", r.width, r.width == 0 or r.width >= 16, "0 (the camera's) or >= 16"),
        ("render.height", r.height, r.height == 0 or r.height >= 16, "0 (the camera's) or >= 16"),
        (
            "render.image_fractions",
            list(r.image_fractions),
            bool(r.image_fractions) and all(0 < x <= 1 for x in r.image_fractions),
            "a non-empty list of values in (0, 1]",
        ),
        ("render.distances_m", list(r.distances_m), all(x > 0 for x in r.distances_m), "positive"),
        ("render.znear_m", r.znear_m, 0 < r.znear_m < r.zfar_m, "positive and below render.zfar_m"),
        ("render.min_elevation_deg", r.min_elevation_deg, -90 <= r.min_elevation_deg < 90, "in [-90, 90)"),
        ("render.paper_azimuth_step_deg", r.paper_azimuth_step_deg, 0 < r.paper_azimuth_step_deg <= 360, "in (0, 360]"),
        ("features.n_features", f.n_features, f.n_features >= 0, ">= 0 (0: no limit)"),
        ("features.contrast_threshold", f.contrast_threshold, f.contrast_threshold > 0, "> 0"),
        ("features.edge_threshold", f.edge_threshold, f.edge_threshold > 0, "> 0"),
        ("features.sigma", f.sigma, f.sigma > 0, "> 0"),
        ("match.prefilter_views", m.prefilter_views, m.prefilter_views >= 1, ">= 1"),
        ("match.prefilter_ratio", m.prefilter_ratio, 0 < m.prefilter_ratio <= 1, "in (0, 1]"),
        ("match.first_views", m.first_views, m.first_views >= 1, ">= 1"),
        ("match.flann_trees", m.flann_trees, m.flann_trees >= 1, ">= 1"),
        ("match.flann_checks", m.flann_checks, m.flann_checks >= 1, ">= 1"),
        ("match.roi_margin_px", m.roi_margin_px, m.roi_margin_px >= 0, ">= 0"),
        ("weights.w_min", conf.weights.w_min, 0 <= conf.weights.w_min <= 1, "in [0, 1]"),
        ("gnc.ransac_reproj_px", g.ransac_reproj_px, g.ransac_reproj_px > 0, "> 0"),
        ("gnc.ransac_iterations", g.ransac_iterations, g.ransac_iterations >= 1, ">= 1"),
        ("gnc.ransac_confidence", g.ransac_confidence, 0 < g.ransac_confidence < 1, "in (0, 1)"),
        ("gnc.kappa", g.kappa, g.kappa > 0, "> 0"),
        ("gnc.epsilon", g.epsilon, g.epsilon > 0, "> 0"),
        ("gnc.tau_gnc", g.tau_gnc, 0 < g.tau_gnc <= 1, "in (0, 1]"),
        ("gnc.tau_geom", g.tau_geom, 0 <= g.tau_geom <= 1, "in [0, 1]"),
        ("gnc.min_inliers", g.min_inliers, g.min_inliers >= 4, ">= 4 (PnP)"),
        ("gnc.mu_final_px", g.mu_final_px, g.mu_final_px > 0, "> 0"),
        ("gnc.max_iterations", g.max_iterations, g.max_iterations >= 1, ">= 1"),
        ("refine.iterations", rf.iterations, rf.iterations >= 0, ">= 0"),
        ("refine.radius_px", rf.radius_px, rf.radius_px > 0, "> 0"),
        ("refine.ratio", rf.ratio, 0 < rf.ratio <= 1, "in (0, 1]"),
        ("refine.mu_final_px", rf.mu_final_px, rf.mu_final_px > 0, "> 0"),
        ("refine.hypotheses", rf.hypotheses, rf.hypotheses >= 1, ">= 1"),
        ("refine.polish_rounds", rf.polish_rounds, rf.polish_rounds >= 1, ">= 1"),
        ("refine.polish_search_px", rf.polish_search_px, rf.polish_search_px >= 1, ">= 1"),
        ("fine.margin", fn.margin, fn.margin >= 0, ">= 0"),
        ("fine.margin_px", fn.margin_px, fn.margin_px >= 0, ">= 0"),
        ("fine.prefilter_views", fn.prefilter_views, fn.prefilter_views >= 1, ">= 1"),
        ("fine.cluster_radius_px", fn.cluster_radius_px, fn.cluster_radius_px > 0, "> 0"),
        ("min_matches", conf.min_matches, conf.min_matches >= 4, ">= 4 (PnP)"),
        ("confidence_inliers", conf.confidence_inliers, conf.confidence_inliers > 0, "> 0"),
        ("confidence_residual_px", conf.confidence_residual_px, conf.confidence_residual_px > 0, "> 0"),
    ):
        if not ok:
            raise ConfigError(f"{where}: {key} must be {need}, got {value}")


def to_dict(conf: Any) -> dict:
    """Plain nested dict (tuples as lists) for YAML/JSON output and hashing."""
    out = dataclasses.asdict(conf)

    def fix(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: fix(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [fix(x) for x in v]
        return v

    return fix(out)


def config_hash(*parts: Any) -> str:
    """Stable short hash of config sections / plain values (for cache keys)."""
    blob = json.dumps([to_dict(p) if dataclasses.is_dataclass(p) else p for p in parts], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    """Apply ``a.b=value`` overrides (value parsed as YAML) to a nested dict, returning a new dict."""
    data = json.loads(json.dumps(data))  # deep copy of plain data
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. gnc.kappa=3")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as e:
            raise ConfigError(f"--set {item!r}: cannot parse value: {e}") from None
        node = data
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"--set {item!r}: the key before '=' is empty or has an empty part, e.g. gnc.kappa=3")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {p} is not a section")
        node[parts[-1]] = value
    return data


def load_yaml(path: Path) -> dict:
    """Read a YAML mapping; missing file or bad YAML raise ConfigError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text (byte {e.object[e.start]:#04x} at offset {e.start})") from None
    except yaml.YAMLError as e:
        msg = str(e).replace("\n", " ")
        raise ConfigError(f"{path}: not valid YAML: {msg}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def load_estimator_config(data: dict, where: str = "pipeline") -> EstimatorConfig:
    return validate(from_dict(EstimatorConfig, data, where), where)
