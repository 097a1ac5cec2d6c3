"""The pipeline's sections: one frozen dataclass per step of the method, each field's type, default, rules
(:func:`~batchpose.config.rules.knob`) and docstring together. Defaults are SPEC.md's values."""

from __future__ import annotations

from dataclasses import dataclass

from batchpose.config.rules import knob


@dataclass(frozen=True)
class MeshConfig:
    """How meshes are loaded."""

    units: str = knob("auto", choices=("auto", "m", "mm"))
    """"m", "mm", or "auto": a bounding-box diagonal > ``mm_diagonal_threshold`` means millimetres."""
    on_millimetres: str = knob("convert", choices=("convert", "refuse"))
    """What to do with a millimetre mesh under ``units: auto``: "convert" (scale 1/1000, warn) or "refuse"."""
    mm_diagonal_threshold: float = knob(5.0, gt=0)
    """Bounding-box diagonal (in file units) above which a mesh is taken to be in millimetres (SPEC §1)."""
    max_texture_px: int = knob(2048, ge=16)
    """Textures larger than this (longer side) are downscaled on load: templates and refinement renders are
    at most a few hundred pixels across, and a 4096² texture costs 64 MB of GL memory per object."""


@dataclass(frozen=True)
class RenderConfig:
    """Template views (SPEC §1)."""

    view_preset: str = knob("sphere", choices=("sphere", "paper"))
    """"sphere": Fibonacci sampling of the whole view sphere; "paper": one azimuth ring at a fixed height."""
    n_views: int = knob(160, ge=1)
    """Viewpoints on the sphere (``sphere`` preset)."""
    min_elevation_deg: float = knob(-90.0, ge=-90, lt=90)
    """Lowest camera elevation above the model's x-y plane (``sphere`` preset); -90 covers the whole sphere."""
    paper_azimuth_step_deg: float = knob(10.0, gt=0, le=360)
    """Azimuth step over [-180, 180) (``paper`` preset)."""
    paper_height_m: float = 1.0
    """Camera height above the model origin (``paper`` preset); the distance is ``distances_m[0]``."""
    distances_m: tuple[float, ...] = knob((), gt=0)
    """Camera distances in metres; empty: chosen per object from ``image_fractions``."""
    image_fractions: tuple[float, ...] = knob((0.5, 0.25), gt=0, le=1, nonempty=True)
    """With automatic distances: the object's diameter spans this fraction of the image's shorter side."""
    width: int = knob(0, ge=16, off="the camera's")
    """Template image width; 0: the data set camera's width (or 640)."""
    height: int = knob(0, ge=16, off="the camera's")
    """Template image height; 0: the data set camera's height (or 480)."""
    shading: str = knob("flat", choices=("flat", "lit"))
    """Template shading of the library every object is matched against first: "flat" (the texture's albedo
    alone) or "lit" (a headlight plus ambient light: curved and turned-away faces shaded, as real frames show
    them)."""
    retry_shading: str = knob("lit", choices=("none", "flat", "lit"))
    """A second template library, rendered with this shading: each object a full estimate does not find, or
    finds only weakly (confidence below ``verify_below``), is matched once more against it with the frame's
    keypoints, and the new pose is kept when it is ok and more confident (before the ``features.retry_*``
    retries, which detect keypoints again). "none" (the ``paper`` and ``fast`` pipelines), or the same as
    ``shading``: one library. The second library is cached like the first. Flat first, lit second, against
    lit alone: ycbv_dev tracked 89.1 / 71.4 -> 90.0 / 73.4 mean ADD-S / ADD AUC, every frame afresh 88.9 /
    69.2 -> 87.9 / 68.6; held-out sequences 78.1 / 70.4 -> 79.5 / 71.6, single frames 80.3 / 71.6 -> 80.0 /
    71.4 (reports/ACCURACY.md, "Template shading")."""
    znear_m: float = knob(0.01, gt=0)
    """Near clipping plane of every render (templates, refinement, checks), metres."""
    zfar_m: float = 20.0
    """Far clipping plane of every render, metres: an object farther away does not show in its render."""


@dataclass(frozen=True)
class FeatureConfig:
    """SIFT features, for templates and queries alike."""

    n_features: int = knob(0, ge=0, note="0: no limit")
    """Keep at most this many keypoints per image (0: all)."""
    contrast_threshold: float = knob(0.02, gt=0)
    """SIFT's contrast threshold: half OpenCV's 0.04, for more keypoints on dim, blurred or small objects
    (the ``paper`` and ``fast`` pipelines keep 0.04; reports/ACCURACY.md has both)."""
    retry_contrast_threshold: float = knob(0.01, ge=0)
    """When a full estimate finds no pose (not found, or below ``min_confidence``) or only a weak one (below
    ``verify_below``), detect the frame's SIFT keypoints again with this lower contrast threshold and
    estimate that object once more (its fine pass inside the object's box too), keeping the new pose if it
    is ok and more confident (0: no retry; the ``paper`` and ``fast`` pipelines). Costs a second detection
    in frames where an object is missing or weak; confidently found objects are never affected. Held-out
    sets (benchmarks/heldout.py) seeds 0 / 1 / 2 / 3: 82.4 / 80.3 / 83.7 / 78.8 without the retry, 88.4 /
    84.3 / 84.8 / 82.7 mean ADD-S AUC with it (85.4 / 85.3 / 85.7 / 80.8 when the fine pass kept the default
    contrast); ycbv_dev unchanged (reports/ACCURACY.md at 8fba8e3, "Session 13" and "Session 14")."""
    retry_sigma: float = knob(1.2, gt=0, off="off")
    """A second retry, for the objects the first one (``retry_contrast_threshold``) did not find either, or
    found only weakly: keypoints detected again at ``retry_contrast_threshold`` with SIFT's base blur at
    this σ instead of ``sigma``, which keeps finer print (0: no second retry; no effect without the first).
    Kept under the first retry's rule: ok and more confident. Held-out seeds 3-14 (2,304 pairs, paired):
    mean ADD-S / ADD AUC 85.3 / 84.0 -> 86.3 / 85.0, no seed lower, 21 more right poses and 13 more wrong
    ones reported ok; fresh seeds 15-16: 83.0 / 81.7 -> 83.8 / 82.7; ycbv_dev and the scale logs unchanged;
    ~15 % more compute per pair on the held-out frames, none on a tracked log (reports/ACCURACY.md at 8fba8e3,
    "Session 25")."""
    edge_threshold: float = knob(10.0, gt=0)
    """SIFT's edge threshold (OpenCV's default): the larger, the fewer edge-like keypoints are dropped."""
    sigma: float = knob(1.6, gt=0)
    """σ of SIFT's base blur of the image (OpenCV's default); see ``retry_sigma``."""
    root_sift: bool = True
    """Use RootSIFT (Arandjelović & Zisserman 2012: L1-normalised, square-rooted) descriptors, compared by
    Euclidean distance = Hellinger kernel; the ``paper`` pipeline keeps SIFT's (reports/ACCURACY.md at 8fba8e3,
    "Session 11")."""
    crop_padding_px: int = 16
    """Templates: run SIFT only on the object's bounding box plus this margin (saves time, same features)."""


@dataclass(frozen=True)
class MatchConfig:
    """2D-3D correspondences (SPEC §2)."""

    direction: str = knob("template_to_query", choices=("template_to_query", "query_to_template"))
    """"template_to_query": ratio test from each template keypoint into the frame's keypoints;
    "query_to_template": from each frame keypoint into the object's template descriptors."""
    ratio: float = knob(0.75, gt=0, le=1)
    """Lowe's ratio-test threshold."""
    distinct_3d_m: float = 0.01
    """query_to_template: the ratio is taken against the nearest neighbour whose 3D point is farther than
    this from the best match's (a second view of the same surface point is not a rival)."""
    top_k_templates: int = knob(3, ge=1)
    """Keep the pairs of the k templates with the most surviving matches."""
    prefilter_views: int = knob(32, ge=1)
    """template_to_query: first vote for views with each frame keypoint's nearest template descriptor and
    test only the keypoints of the ``prefilter_views`` most-voted views (0: test every view). On ycbv_dev
    32 views halve the time per pair with no accuracy change beyond run-to-run noise."""
    prefilter_ratio: float = knob(0.9, gt=0, le=1)
    """Loose ratio test a frame keypoint must pass to vote for a view (see ``prefilter_views``)."""
    first_views: int = knob(8, ge=1)
    """Whole-frame pass with ``prefilter_views``: test the keypoints of this many most-voted views first and
    the other views' only when those do not give a strong pose (``strong_inliers``); the pairs are then
    exactly those of all ``prefilter_views`` views. A strong object is matched ~4x faster (0: off)."""
    flann_trees: int = knob(4, ge=1)
    """Randomised k-d trees of each FLANN descriptor index."""
    flann_checks: int = knob(32, ge=1)
    """Leaves FLANN visits per nearest-neighbour query (more: slower, nearer to an exact search)."""
    roi: str = knob("none", choices=("none", "gt_box"))
    """"none": whole image; "gt_box": oracle box from ground truth (evaluation only, never default)."""
    roi_margin_px: int = knob(24, ge=0)
    """``roi: gt_box``: the box of the template keypoints projected at the true pose, grown by this many pixels."""
    presence_votes: int = knob(5, ge=0)
    """Which objects are in the frame, decided once per frame before the expensive steps
    (:mod:`batchpose.method.presence`): the frame's keypoints are looked up once in one index over every
    object's templates; a keypoint counts for the object of its nearest template descriptor when it passes
    the ratio test against the nearest of another object (or another point of the same one), and an object
    whose keypoints agree on no location (centre, size, in-plane rotation) with at least this many votes is
    reported ``absent``, without the matching passes, retries and refinement (the plane search may still
    find it: ``plane.search_absent``). 0: off (every object gets the full estimate). Only where the run
    does not know which objects a frame shows (``targets: all``): under ``targets: annotations`` the ground
    truth lists them."""
    presence_checks: int = knob(24, ge=1)
    """``flann_checks`` of the presence check's query (which ``joint_vote`` reuses). A vote count tolerates a
    less exact search than the matching does: on ycbv_dev's 66 frames 24 against 32 changes none of the 198
    decisions for three objects and 6 of 792 for twelve (3 present objects kept, 1 absent one let through to
    the full estimate), at 0.8x the query's time."""
    joint_vote: bool = True
    """With the presence check on: the whole frame's keypoints vote for an object's views (and the locator's
    Hough votes) from the joint index's answer, which the presence check asked already, instead of asking
    the object's own library again. A keypoint then counts only when its nearest descriptor is this object's
    and it passes the ratio test against the nearest of another object too."""


@dataclass(frozen=True)
class WeightsConfig:
    """Geometry-aware weights (SPEC §3)."""

    mode: str = knob("correspondences", choices=("correspondences", "model", "none"))
    """"correspondences": voxel support over this frame's 3D points; "model": support over all template
    keypoints of the library; "none": every weight is 1 (the no_geom_weights ablation)."""
    voxel_m: float = knob(0.005, gt=0)
    """Side of the voxels in which a correspondence's 3D support is counted, metres."""
    w_min: float = knob(0.2, ge=0, le=1)
    """Weight of the least supported correspondence: w = w_min + (1 - w_min) * support / max support."""


@dataclass(frozen=True)
class GncConfig:
    """RANSAC initialisation, GNC-PnP with dual-filter inlier selection, final LM (SPEC §4)."""

    enabled: bool = True
    """False: RANSAC-PnP + LM only (the ransac_only ablation)."""
    ransac_reproj_px: float = knob(8.0, gt=0)
    """RANSAC-PnP (EPnP) inlier threshold, pixels; also the inlier set after the RANSAC pose's LM polish."""
    ransac_iterations: int = knob(1000, ge=1)
    """Most RANSAC-PnP iterations."""
    ransac_confidence: float = knob(0.999, gt=0, lt=1)
    """RANSAC-PnP stops once it has drawn an all-inlier sample with this probability."""
    residual: str = knob("pixels", choices=("pixels", "squared"))
    """"pixels": r = ||proj - x||; "squared": r = ||proj - x||^2."""
    kappa: float = knob(5.0, gt=0)
    """GNC's initial scale: mu0 = kappa * median residual (over ``mu0_from``) + ``epsilon``."""
    epsilon: float = knob(1e-6, gt=0)
    """Keeps mu0 above 0 when the residuals are."""
    mu0_from: str = knob("ransac_inliers", choices=("all", "ransac_inliers"))
    """Median for mu0 over "all" correspondences (the paper) or over the RANSAC inliers."""
    tau_gnc: float = knob(0.5, gt=0, le=1)
    """A pair is selected when its GNC weight mu² / (r² + mu²) exceeds this ..."""
    tau_geom: float = knob(0.25, ge=0, le=1)
    """... and its geometry-aware weight (``weights``) exceeds this: the dual filter."""
    min_inliers: int = knob(6, ge=4, note="PnP")
    """Fewest RANSAC inliers for a pose (else pnp_failed); GNC stops when it would select fewer."""
    gamma: float = knob(0.5, gt=0, lt=1)
    """GNC shrinks mu by this factor each iteration ..."""
    mu_final_px: float = knob(0.5, gt=0)
    """... down to this, where it stops."""
    max_iterations: int = knob(50, ge=1)
    """Most GNC iterations (a PnP solve over the selected pairs each); it also stops when the selection repeats."""
    final_lm: bool = True
    """Polish the pose by Levenberg-Marquardt over the final inliers."""


@dataclass(frozen=True)
class RefineConfig:
    """Render-and-match refinement (batchpose's addition; see :mod:`batchpose.method.refine`)."""

    enabled: bool = True
    """Refine every pose by matching the frame against the mesh rendered at that pose."""
    iterations: int = knob(2, ge=0)
    """Rounds of render -> SIFT -> guided matching -> PnP."""
    radius_px: float = knob(12.0, gt=0)
    """A rendered keypoint matches only frame keypoints within this many pixels of it."""
    ratio: float = knob(0.85, gt=0, le=1)
    """Ratio test among the frame keypoints within the radius."""
    mu_final_px: float = knob(1.5, gt=0)
    """GNC's final scale for the guided pairs (their keypoint noise is real-image noise, not 0.5 px)."""
    gnc: bool = True
    """Solve the guided pairs with GNC (as ``gnc.enabled``); false: RANSAC-PnP + LM over all its inliers."""
    hypotheses: int = knob(4, ge=1)
    """Also refine poses solved from each of the best templates alone, up to this many hypotheses in all,
    and keep the one with the most guided inliers."""
    same_start_px: float = knob(2.0, ge=0)
    """A starting pose that projects the object's bounding box less than this many pixels from an earlier
    start's is not refined again: the guided matching (``radius_px``) finds the same pairs from both, so it would
    reach the same pose. 0 refines every start."""
    flips: bool = True
    """Also try the best hypothesis turned 180 degrees about each of the mesh's principal axes (the poses a
    texture-symmetric object is most often confused with); keep whichever has the most guided inliers."""
    polish: bool = False
    """Finish every full estimate with a dense render-and-compare alignment (``method.hypotheses.polish``):
    corners of the frame on the mesh rendered at the pose are found again, by normalised cross-correlation
    within ``polish_search_px``, in that render, and the pose is solved again by Levenberg-Marquardt from
    them (the tracker's ``track.render_every`` step), ``polish_rounds`` times. It sharpens the distance
    along the line of sight where the mesh and the calibration match the images exactly: unseen held-out
    frames (rendered meshes, seeds 3-14) 85.3 / 84.0 -> 86.1 / 85.3 mean ADD-S / ADD AUC, median ADD 1.5 ->
    0.9 mm. On ycbv_dev's real frames it moves poses farther still from the ground truth and the depth
    sensor (90.5 / 79.1 -> 88.9 / 76.5, the tracked frames following it too; reports/ACCURACY.md at 8fba8e3,
    "Session 23"), so it is off by default. Costs a render and about 200 patch searches a round, for full
    estimates only."""
    polish_rounds: int = knob(3, ge=1)
    """Render, search and solve rounds of ``polish``; each starts from the last round's pose."""
    polish_search_px: int = knob(4, ge=1)
    """How far from where the pose projects it a corner's rendered patch is looked for."""


@dataclass(frozen=True)
class FineConfig:
    """Coarse-to-fine matching (batchpose's addition): after the whole-frame pass, find the object's box
    and match again inside it, upsampled, against every template view."""

    enabled: bool = True
    """Run the fine pass (false: the whole-frame pass only)."""
    upsample: float = knob(2.0, ge=1)
    """Scale the crop by this factor before SIFT (small, blurred objects give few keypoints at 1x)."""
    max_side_px: int = knob(1024, ge=32)
    """Lower the upsampling factor so the scaled crop's longer side stays within this."""
    margin: float = knob(0.15, ge=0)
    """Grow the box by this fraction of its size on every side (the coarse pose may be off)."""
    margin_px: int = knob(16, ge=0)
    """... plus this many pixels."""
    max_box_fraction: float = knob(1.0, gt=0, le=1)
    """No fine pass in a box over this fraction of the image (1: no limit). 0.5 saved ~5 % on the cycling log but
    lost a dim object on held-out seed 3 that only that upsampled whole-frame pass found (reports/BENCHMARKS.md)."""
    prefilter_views: int = knob(32, ge=1)
    """Views tested inside the box, chosen by the crop's keypoints' votes as in ``match.prefilter_views``
    (0: every view, which costs about twice the time for no measured gain on ycbv_dev)."""
    cluster_radius_px: float = knob(48.0, gt=0)
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
    locate_votes: int = knob(4, ge=1)
    """Fewest agreeing keypoints for a location."""
    locate_ratio: float = knob(0.8, gt=0, le=1)
    """Ratio test (against the nearest descriptor of another 3D point) for a frame keypoint to vote."""
    # The older wording of this error, which tests/test_fine.py matches.
    locate_peaks: int = knob(1, ge=1, subject="fine.locate_peaks and fine.locate_votes")
    """Locations searched: the fullest vote cell, then the fullest among the votes it leaves, ... (one fine
    pass each, skipping a box already searched). 2 measured no gain on benchmarks/heldout.py (68.2/65.5
    against 68.0/65.6, 16 frames/object, seed 1) for 25 % more estimate time."""
    locate_pairs: bool = True
    """Add the agreeing votes' 2D-3D pairs to the pairs matched in the located box."""
    locate_angle_deg: float = knob(30.0, ge=0, le=180)
    """Width of the in-plane rotation bins (0: do not vote on rotation). Chance matches agree on a
    place less often when they must also agree on the object's in-plane rotation."""


@dataclass(frozen=True)
class TrackConfig:
    """Frame-to-frame tracking (batchpose's addition; see :mod:`batchpose.method.track`): a confident pose is
    followed into the next frames with optical flow and PnP instead of being estimated afresh."""

    enabled: bool = True
    """Follow confident poses into the next frames (false: a full estimate in every frame)."""
    max_gap_s: float = knob(0.25, gt=0)
    """Follow a pose only into a later frame of the same scene and camera at most this many seconds on."""
    min_confidence: float = 0.5
    """Start a track only from a full estimate at least this confident."""
    redetect_every: int = knob(0, ge=0)
    """Estimate afresh after this many tracked frames (0: only when the track is lost or the worker task
    ends, i.e. at least every ``chunk_frames`` frames)."""
    points: int = knob(200, ge=1)
    """Corners seeded on the object at the keyframe."""
    quality: float = 0.01
    """Shi-Tomasi quality level of a seeded corner (fraction of the strongest corner's score)."""
    min_distance_px: float = 5.0
    """Seeded corners are at least this far apart."""
    min_ncc: float = knob(0.5, ge=-1, le=1)
    """A corner is seeded only where the frame correlates with the mesh rendered at the pose at least this
    much (normalised cross-correlation of the patches): corners on an occluder are not the object."""
    ncc_radius_px: int = knob(5, ge=1)
    """Half-side of the patches compared for ``min_ncc``."""
    min_points: int = knob(12, ge=6, note="PnP")
    """A track is lost with fewer surviving points than this ..."""
    min_fraction: float = knob(0.5, ge=0, le=1)
    """... or than this fraction of its seeded points."""
    anchor: bool = True
    """Also flow each point straight from the keyframe (started where frame-to-frame flow ended), so that
    flow errors do not add up over a track."""
    anchor_px: float = 2.0
    """Use the keyframe flow where it lands within this many pixels of the frame-to-frame flow."""
    occlusion_margin_px: int = knob(10, ge=-1)
    """When two tracked objects overlap in the image, drop each one's points that lie within this many
    pixels of the other's image region (its convex hull projected at its last pose) and are farther from the
    camera than the other's nearest point (-1: keep them). Lucas-Kanade follows texture, so a point that an
    object moving in front covers is dragged along with it, and with it the pose. The margin covers a
    frame's motion and the flow window. Dropped points count as never seeded, so hiding part of an object
    does not by itself end its track."""
    render_every: int = knob(0, ge=0)
    """Every this many tracked frames, pull the points back onto the mesh: find each point's patch of the
    mesh rendered at the tracked pose in the frame (NCC within ``render_search_px``) and solve again
    (0: never)."""
    refresh_every: int = knob(32, ge=0)
    """After this many tracked frames (or when fewer than ``reseed_fraction`` of the points survive), make
    the tracked frame a new keyframe instead of estimating afresh: pull the pose onto the mesh rendered there
    (as ``render_every``; the track ends if too few points are found) and seed new corners (0: never).
    Costs a render and a seeding (~3 % of a full estimate) and removes the flow's drift, which is what lets
    ``chunk_frames`` be 64."""
    reseed_fraction: float = knob(0.75, ge=0, le=1)
    """See ``refresh_every``."""
    refresh_turn_deg: float = knob(20.0, ge=0, le=180)
    """Refresh also when the camera has moved this far around the object since the keyframe (the angle
    between the two directions from the object to the camera; 0: never for that reason): the points
    seeded on the sides it showed then do not cover the sides it shows now."""
    min_match: float = knob(0.35, ge=0, lt=1)
    """A track starts, and survives a refresh, only where the mesh rendered at its pose looks like the
    frame over its whole silhouette (texture match, as ``verify_min_match``, over the pixels no object
    found in front hides); else the object is estimated afresh in the next frame, or at once at a
    refresh (0: no check). A wrong but confident full estimate would otherwise be followed for dozens of
    frames; and a track's points all lie on what was visible at its keyframe: when the object turns that
    part edge-on they can stay aligned while the pose turns the wrong way, which the pull onto the mesh,
    looking only near each point, cannot see."""
    render_search_px: int = knob(3, ge=1)
    """How far from its tracked position a point's rendered patch is looked for."""
    depth_prior: float = knob(1.0, ge=0)
    """Each followed pose (and a thin track's pulled onto the rendered mesh at a new keyframe) is solved with
    its change of depth since the previous frame costing as much as this many points would if the points' rim
    moved as far in the image as that change makes it grow or shrink (0: no prior). A few points along a thin
    object, lifted at a pose a little off, do not pin the depth: a marker's track slid 0.11 -> 0.49 d along
    the line of sight in three frames without it, and stays at 0.11-0.13 d with it; where the points pin the
    depth it moves the pose by a fraction of a pixel (reports/ACCURACY.md, "Tracking a thin object"). About
    1 ms a track a frame."""
    fb_max_px: float = 1.0
    """A point survives a frame when optical flow back from its new position lands this close to the old."""
    reproj_px: float = 3.0
    """... and its reprojection error at the tracked pose is at most this."""
    window_px: int = knob(15, ge=5)
    """Lucas-Kanade window side. Corners are seeded at least half of it inside the object's silhouette, so that
    no window reaches over the outline (the background there does not move with the object) ..."""
    thin_margin_px: int = knob(0, ge=0)
    """... except, when this is over 0 (and under ``window_px // 2``), where that leaves fewer than
    ``min_points`` corners, a thin object (a pen 20 px wide keeps a strip of 6 px): then they are seeded this
    far inside its outline (2 does it), the track is marked thin, and each pull of it onto the rendered mesh
    holds its depth (``depth_prior``). Off (0) by default: a thin object's first SIFT pose is often wrong
    along the line of sight (a pen's image length fits a nearer, more tilted pen as well), and its track
    repeats that pose in every frame it follows, in place of full estimates that may get it right. On the
    held-out sequences 2 made 14 pairs ok in seeds 3-6, all right, and in seed 7 made 10 ok, all 0.21-0.32 d
    off the pose the image shows, and turned three right ones there wrong (reports/ACCURACY.md, "Tracking a
    thin object")."""
    levels: int = knob(3, ge=0)
    """Lucas-Kanade pyramid levels above the full image."""
    lost_full_every: int = knob(4, ge=1)
    """While an object stays lost (its estimates start no track) in consecutive frames, only every this
    many-th of them gets the full estimate; the others get a quick one: the whole-frame pass against the
    ``match.first_views`` most-voted views only, and one refinement of its pose (~3x cheaper). An object
    counts as lost until a track of it lives this many frames. An occluded or absent object
    then costs a third of the time; one that reappears is found up to this many frames later where only
    the fine pass or locator finds it. 1: always the full estimate."""
    hidden_above: float = knob(0.6, gt=0, le=1)
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
    (reports/BENCHMARKS.md at 8fba8e3, session 18) the further object's cost rises from +0.2x to +0.47x the floor, and
    the fine pass finds a mostly hidden object in a few more frames (ADD < 0.1 d 95.4 -> 95.8 % of the log's
    pairs)."""
    hidden_retry: bool = False
    """Give those full estimates of a mostly hidden object ``features.retry_contrast_threshold``'s retry
    too. Off: the object was not found because it is hidden, not for want of contrast, and the retry (SIFT
    at the lower threshold, then a second full estimate) more than doubles the estimate's time."""
    chunk_frames: int = knob(64, ge=1)
    """Frames per worker task while tracking. A track never crosses tasks, so results do not depend on
    ``--jobs``; each task starts with a full estimate per object. Two-object benchmark log (800 frames,
    reports/BENCHMARKS.md): 32 frames without refreshes 93.8 ADD AUC at +0.72x the floor per further
    object; 64 with ``refresh_every`` 32: 94.9 at +0.47x; 128: tracks drift (ADD < 0.1 d 93 -> 88.5 %)
    and a short log splits into too few tasks to share between workers."""
    min_chunks: int = knob(4, ge=1)
    """A run of fewer than ``min_chunks`` x ``chunk_frames`` frames is cut into ``min_chunks`` shorter
    tasks, so that a short run keeps every worker busy (17 frames in one 64-frame task left one of two
    workers idle). It depends on the run's frame count only, not on ``--jobs``: results stay the same for
    any number of workers."""


@dataclass(frozen=True)
class CarryConfig:
    """Carrying confident poses through a recorded log, forwards and backwards (batchpose's addition; the
    ``carry`` stage, :mod:`batchpose.method.carry`): after every frame is estimated, an object missed in a
    frame next to one where it was found confidently is followed into it by the tracker (optical flow from
    the neighbour's pose, then the pull onto the mesh and its check), in either direction, and on from there;
    each carried pose is checked as a tracked one is and then as a weak full estimate is. Estimation cuts a
    run into tasks that start without memory and tracks only forwards; this finds what neither reaches."""

    enabled: bool = True
    """Run the carry stage (false: the poses are the estimate stage's)."""
    min_confidence: float = knob(0.5, ge=0, le=1)
    """Carry only from an ok pose at least this confident (as ``track.min_confidence`` starts a track); a
    carried pose keeps its source's confidence at most, so a chain goes on only while it stays this
    confident."""
    max_steps: int = knob(32, ge=1)
    """Carry a pose at most this many frames from the confident pose it started from (each direction)."""
    into_absent: bool = True
    """Also carry into pairs whose status is ``absent`` (the presence check found no SIFT evidence of the
    object: a weakly textured or blurred object next to a frame where it was found confidently is there all
    the same). Each carried pose passes the tracker's checks against the rendered mesh frame by frame, so an
    object that has left the view or is covered is not carried into it. False: carry only into the statuses
    of an object looked for and not found (too_few_matches, pnp_failed, low_confidence) and ``hidden``."""
    over_weak: bool = True
    """Also carry into pairs whose estimate is a weak ok pose: untracked, under ``min_confidence`` here (a
    retry's or a search's pose that could not start a carry itself). The carried pose replaces it only where
    the verification score prefers it (``min_verification`` > 0: without the score nothing is compared), so
    a weak pose that disagrees with the confident ones of the frames beside it (a can found upside down and
    a can's height away by the lowest-contrast retry) gives way to the pose they carry in."""


@dataclass(frozen=True)
class DepthConfig:
    """Optional use of a depth image registered to the colour image (batchpose's addition; see
    :mod:`batchpose.method.depth`). The RGB estimate is unchanged; each pose it finds is then moved along its
    viewing ray onto the sensor's depth and aligned to it (robust point-to-plane ICP on the object's pixels),
    which fixes the weak axis of a monocular pose, the distance along the viewing ray. Frames without a depth
    image keep their RGB poses."""

    enabled: bool = False
    """Align every RGB pose to the frame's depth image, where it has one."""
    level: int = knob(2, ge=1)
    """Work on every ``level``-th pixel of the depth image (and of the renders): ~2x cheaper at 2 than at 1,
    with ample points for a 6-DoF fit."""
    iterations: int = knob(8, ge=1)
    """ICP iterations (the object's pixels are chosen anew at each)."""
    gate_m: float = knob(0.03, gt=0)
    """A pixel is the object's when its sensor depth is within this of the mesh rendered at the pose: at the
    first iteration ..."""
    gate_final_m: float = knob(0.01, gt=0)
    """... narrowing linearly to this at the last."""
    ray_align: bool = True
    """Before the ICP and before any check, move the pose along the viewing ray through the object's centre
    (its translation scaled, so its projection stays) to where the rendered surface meets the sensor's depth
    on most of the silhouette (:func:`batchpose.method.depth.along_ray`): a monocular pose 2-5 cm too far at
    ~1 m is beyond the ICP's first gate (``gate_m``) and would otherwise be judged, and rejected, where the
    sensor sees nothing of it (ycbv_dev's real-frame poses pushed 4 cm: 160 of 160 kept, 28 without; a pose
    laid onto a plain wall is not moved). False: the ICP and the checks start from the RGB pose."""
    ray_range: float = knob(0.15, gt=0, lt=1)
    """How far the ray alignment may move the object: this fraction of its distance, nearer or farther (a
    pose whose readings run on past it is not moved)."""
    min_pixels: int = knob(50, ge=6)
    """Fewer object pixels with a sensor reading than this: the pose is left as the RGB estimate (or the ray
    alignment) gave it."""
    max_points: int = 1500
    """Depth pixels on and around the object used (evenly subsampled)."""
    damping: float = knob(0.05, ge=0)
    """Levenberg damping of the ICP step (relative): directions the depth cannot see, such as a can's turn
    about its axis or a box's on its flat face, stay where the RGB estimate put them (at 0.001 the ICP
    turned right box poses 23-28 degrees on the held-out set; the depth search aligns with 0.001)."""
    max_shift: float = knob(0.25, gt=0)
    """An alignment that moves the object's centre by more than this fraction of its diameter, or turns it by
    more than ``max_turn_deg``, is not used: the RGB pose and the depth disagree about which surface it is."""
    max_turn_deg: float = knob(20.0, gt=0)
    """See ``max_shift``."""
    max_see_through: float = knob(0.5, ge=0, le=1)
    """With more than this fraction of the object's silhouette showing sensor depth farther than the object
    (the camera sees past where the pose puts it), the pose contradicts the depth: status pnp_failed.
    Nearer readings are occluders and do not count (1: never fail a pose)."""
    min_agree: float = knob(0.1, ge=0, le=1)
    """With less than this fraction of the silhouette's readings within a quarter of the object's diameter of
    the rendered surface, the pose contradicts the depth too: the sensor sees the object nowhere there, e.g.
    a pose far behind the objects in front of it (0: never fail a pose)."""
    search: bool = False
    """Look for an object the RGB estimate did not find (or whose pose the depth contradicts) by colour
    and depth (:mod:`batchpose.method.depth_search`, ~3–10 s an object). A pose found this way has reason
    "found by the depth search" and confidence at most 0.5."""
    search_view_step: int = knob(4, ge=1)
    """Use every this-many-th library view (at the nearest distance) as a silhouette."""
    search_angles: int = knob(12, ge=1)
    """In-plane turns of each silhouette."""
    search_hypotheses: int = knob(5, ge=1)
    """Places aligned to the depth (each also turned 180 degrees about the mesh's three principal axes)."""
    search_polish: int = knob(3, ge=0)
    """The best-fitting this-many distinct hypotheses whose texture lines up at all are turned about their
    principal axes (20, 10, 5 degrees) and aligned again while that fits better (0: keep the best as
    aligned); the best that passes the checks below is kept."""
    search_min_visible: float = knob(0.4, ge=0, le=1)
    """Keep a found pose only if the sensor sees at least this fraction of its silhouette at its surface ..."""
    search_max_see_through: float = knob(0.1, ge=0, le=1)
    """... sees past at most this fraction ..."""
    search_min_colour: float = 1.2
    """... the seen pixels have the object's colours: mean log-odds of their colours under the object's
    colour histogram against the frame's outside the silhouette at least this (1.2: 3.3 times likelier) ..."""
    search_min_match: float = knob(0.35, ge=-1, le=1)
    """... and in the right places: the mesh rendered at the pose correlates (normalised, in Lab) with the
    frame over the seen pixels at least this well. A flat face laid onto a wall of similar colours fits the
    depth and the histogram but not the texture's layout (-0.02 there); objects found right on ycbv_dev and
    the held-out set 0.47-0.9, absent objects kept on ycbv_dev's synthetic frames 0.30 (a tomato soup can
    on a tuna can, a large marker) and 0.52 (the pudding box on the gelatin box, both Jell-O boxes)."""


@dataclass(frozen=True)
class RegionConfig:
    """One image region belongs to one object (batchpose's addition; :mod:`batchpose.method.region`): after
    every object of a frame is estimated, two ok poses that claim the same pixels and cannot both be right
    are settled by comparing each mesh, rendered at its pose, with the frame; the loser is ``conflict``."""

    max_overlap: float = knob(0.5, gt=0, lt=1, off="no check")
    """Two ok poses are compared when their rendered silhouettes share more than this fraction of the
    smaller silhouette. A real occlusion (the nearer object hides the farther one where the farther one has
    no evidence: inlier keypoints or tracked points) passes; two poses at the same pixels whose evidence
    lies where the other one shows, or whose depth order says the opposite, cannot both be right. 0: off
    (the ``paper`` pipeline and its ablations)."""
    max_hidden_evidence: float = knob(0.25, gt=0, lt=1)
    """The farther of two overlapping poses may have its evidence (inlier keypoints, or tracked points) inside
    the nearer one's silhouette at most this dense (per pixel, against its density over its own silhouette):
    those pixels show the nearer object, so they cannot be the farther one's features. About 1 when two
    poses claim the same keypoints, about 0 for a real occlusion."""
