"""The plane search's section (:class:`PlaneConfig`), in its own module beside :mod:`.sections`: each
field's type, default, rules (:func:`~batchpose.config.rules.knob`) and docstring together."""

from __future__ import annotations

from dataclasses import dataclass

from batchpose.config.rules import knob


@dataclass(frozen=True)
class PlaneConfig:
    """Looking for an object SIFT missed on the surface the found objects rest on (batchpose's addition; see
    :mod:`batchpose.method.plane`). Runs only for an object without a pose in a frame where at least
    ``min_objects`` others were found confidently and rest on one plane; not where ``depth.search`` has a depth
    image to search with."""

    enabled: bool = True
    """Search the support plane for objects SIFT missed."""
    search_absent: bool = False
    """Search it also for the objects ``match.presence_votes`` found no SIFT evidence of (status ``absent``).
    An object with little texture can be there without any SIFT evidence (the mustard bottle's plain back in
    ycbv_dev's video 0001, found only this way), but every absent object in a frame with a plane then costs a
    plane search (seconds), and on the 12-object benchmark of reports/BENCHMARKS.md the searches put a large
    marker on the table in 4 of 44 frames without one. Off: an absent object costs only the presence check."""
    min_objects: int = knob(2, ge=2)
    """Fewest confidently found objects that define a support plane ..."""
    all_objects: bool = False
    """... and True: every one found must rest on it (False: the most that rest on one plane do)."""
    one_object_tilt_deg: float = knob(45.0, ge=0, lt=90)
    """... or one, resting on its face whose upward normal is nearest the image's up direction, if within this
    angle and clearly nearest (:func:`batchpose.method.support.one_object_plane`; 0: two objects needed)."""
    min_confidence: float = knob(0.5, ge=0, le=1)
    """... each at least this confident ..."""
    max_spread_m: float = knob(0.03, gt=0)
    """... whose lowest points along the plane's normal are at most this far apart (poses on real frames are
    1-3 % off in distance; ycbv_dev's video 0001: 11-13 mm)."""
    plane_candidates: int = knob(64, ge=1)
    """Normals tried: each found object's this many largest convex-hull faces, turned downwards."""
    min_stable: float = knob(0.02, ge=0, le=1)
    """Resting faces of the object looked for: its stable poses (trimesh) at least this probable. A bottle
    upright is one of its less probable ones (0.04 for the mustard bottle)."""
    angles: int = knob(12, ge=1)
    """Turns about the plane's normal tried for each resting face."""
    min_span_px: float = knob(12.0, ge=1)
    """Places where the object would span fewer pixels are not searched."""
    starts: int = knob(4, ge=1)
    """Best distinct placements of the coarse search refined."""
    colour_weight: float = knob(0.2, ge=0)
    """Weight of the mean colour log-odds against the texture correlation in the refinement's score."""
    min_visible: float = knob(0.3, gt=0, le=1)
    """A placement is kept if at least this fraction of its silhouette is not hidden by a found object ..."""
    occluder_cuts: tuple[float, ...] = knob((0.25, 0.4), gt=0, lt=1)
    """An object not asked for can stand in front of the one looked for, and nothing explains its pixels. Where
    no placement passes the checks judged whole, the refined placements are judged again, each also with the
    lowest of these fractions of its silhouette (along the plane's up direction in the image: a nearer object
    on the same surface hides the lower part) left out as hidden where that band's colours are not the
    object's (mean colour log-odds under 0), the best of its judgements counting, and refined and checked
    again so. The mustard bottle of ycbv_dev's video 0001 behind the sugar box not asked for: at the
    truth, visible 1.00, colour -0.33, texture 0.25 whole; 0.58, 0.98, 0.44 with the lowest 0.4 left out
    (0.61, 1.08, 0.47 with the sugar box asked for). (): the whole silhouette only."""
    min_colour: float = 0.5
    """... those pixels' mean colour log-odds (the object's histogram against the frame's outside the found
    objects) is at least this ..."""
    min_match: float = knob(0.35, ge=-1, le=1)
    """... the mesh rendered there correlates (Lab) with the frame over them at least this well ..."""
    min_contrast: float = knob(1.5, ge=0)
    """... and it stands out: their mean colour log-odds exceeds that of the 4-px ring around the silhouette
    (found objects left out) by at least this. On ycbv_dev the mustard bottle found 3.0-3.9; objects the
    frame does not show, placed where the colours and texture fit best (a white marker on the white table,
    a can on the mustard bottle), 0.3-1.0."""
    edge_weight: float = knob(0.5, ge=0)
    """Weight of the edge score (:attr:`batchpose.method.plane.Placed.edge`: how closely the frame's edges follow
    the placed silhouette's outline) in the refinement's score (0: not looked at while refining). It also
    aligns wrong placements with edges near them, hence ``min_edge``'s 0.6."""
    min_edge: float = knob(0.6, ge=0, le=1)
    """A placement is kept only if its edge score is at least this (0: not checked; nor where the frame has
    no edges near the placement at all). At their true poses the tabletop's markers and bleach cleansers have
    0.67-0.97 of their outline within 1.5 px of an edge; with ``edge_weight`` 0.5 the
    placements of absent objects that passed every other check scored 0.40-0.62 (tabletop seeds 0-2; this
    value was chosen from them). Tabletop seeds 0-3 against 0: right 20 -> 23, wrong 2 -> 1, absent 2 -> 1."""
    edge_confirms: float = knob(0.75, ge=0, le=1)
    """A finely refined placement that fails one of the two colour checks (``min_colour``, ``min_contrast``)
    is kept if its edge score is at least this: a pale bottle on a white table has the table's colours, a thin
    marker a pixel aside has its own pixels in the contrast's ring. 0: off. Chosen between the edges of the
    truth (0.67-0.97) and of absent objects' placements (90 % under 0.41); with the border fix of session 28,
    tabletop seeds 0-7 replayed: right 39 -> 52, wrong 4 -> 1, absent objects placed 2 -> 2
    (reports/ACCURACY.md at 8fba8e3, "Session 28")."""
    reface: bool = True
    """Also refine, at each coarsely refined start's place, the two best of the object's other resting faces
    with its long axis kept (a bottle lying on its other side, a box on its back): the silhouette barely
    differs, the texture does. Tabletop seeds 1-4 with and without it: +0.71, 0.00, +0.84 and -0.10 pairs of
    credit. It doubles the search's time (2.9 -> 5.1 s). False: the coarse search's faces only."""
