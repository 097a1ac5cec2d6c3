"""One frame in, one pose record per target object out: :class:`PoseEstimator`.

``estimate_image`` is the library call (one RGB image, no memory) and raises :class:`BatchposeError` on bad
input; ``estimate_frame`` is the batch call: it turns every failure into a record and, given the
:class:`~batchpose.method.sequence.Sequence` the caller keeps, follows what earlier frames found. One frame
goes through these steps (docs/method.md):

1. decode the image, and resize it to the working size (``max_image_side_px``);
2. estimate: tracked (:func:`batchpose.method.tracked.estimate_tracked`: follow, estimate the rest afresh,
   seed) or fresh (:func:`batchpose.method.single.estimate_image`);
3. the weak-pose check (:func:`batchpose.method.verify.verify_weak`);
4. the verification score (:func:`batchpose.method.score.verify_poses`), and the retries for an object whose
   pose it rejects (:func:`batchpose.method.single.retry_rejected`);
5. one image region, one object (:func:`batchpose.method.region.claim_regions`);
6. depth: alignment and search (:func:`batchpose.method.with_depth.use_depth`);
7. the plane search (:func:`batchpose.method.on_plane.use_plane`), and the verification score of the poses
   the searches found;
8. back to the full frame's pixels, and the frame's ids on every record.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from collections.abc import Mapping

import cv2
import numpy as np

from batchpose.config import EstimatorConfig
from batchpose.core.frames import Camera, Frame, ObjectPose, decode_image, working_camera
from batchpose.core.poses import PoseRecord
from batchpose.errors import BatchposeError
from batchpose.method.objects import Objects
from batchpose.method.on_plane import use_plane
from batchpose.method.records import FAILED, Replaced, failure_status, to_full_size
from batchpose.method.region import claim_regions
from batchpose.method.score import verify_poses
from batchpose.method.sequence import Sequence
from batchpose.method.single import estimate_image, has_retries, retry_rejected
from batchpose.method.templates import TemplateLibrary
from batchpose.method.tracked import estimate_tracked
from batchpose.method.verify import verify_weak
from batchpose.method.with_depth import use_depth

log = logging.getLogger("batchpose")


class PoseEstimator:
    """Estimates poses of objects whose template libraries it holds.

    Args:
        conf: estimator config.
        libraries: obj_name -> TemplateLibrary.
        obj_ids: obj_name -> numeric id for records (BOP obj_id); optional.
        models: obj_name -> ObjectModel, needed (with ``renderer``) for ``refine.enabled``.
        renderer: a :class:`batchpose.method.render.Renderer` (or anything with its ``render`` method).
        retry_libraries: obj_name -> its second library (``render.retry_shading``); optional.
    """

    def __init__(
        self,
        conf: EstimatorConfig,
        libraries: dict[str, TemplateLibrary],
        obj_ids: dict[str, int] | None = None,
        models: dict | None = None,
        renderer=None,
        retry_libraries: Mapping[str, TemplateLibrary] | None = None,
    ) -> None:
        self.conf = conf
        self.objects = Objects(conf, libraries, obj_ids, models, renderer, retry_libraries)

    def warm_up(self) -> None:
        """Build every object's library index and render each mesh once (:meth:`Objects.warm_up`)."""
        self.objects.warm_up()

    def tracking(self) -> bool:
        """True when :meth:`estimate_frame` follows confident poses into the next frames (``track.*``)."""
        return self.objects.tracking()

    # -- library call ----------------------------------------------------------------------------
    def estimate_image(
        self,
        rgb: np.ndarray,
        camera: Camera,
        obj_names: list[str],
        gt: tuple[ObjectPose, ...] = (),
        frame_id: str = "image",
        quick: frozenset[str] = frozenset(),
        no_retry: frozenset[str] = frozenset(),
    ) -> list[PoseRecord]:
        """Estimate every object in ``obj_names`` in one RGB image.

        Args:
            rgb: (H, W, 3) uint8 RGB.
            camera: calibration of this image.
            obj_names: objects to look for (each must have a library).
            gt: ground-truth poses, used only by the ``match.roi: gt_box`` oracle and ``method: tp_ub``.
            quick: objects estimated as if the whole-frame pass were strong (its first stage only, no fine
                pass or locator, one refinement hypothesis): tracking's cheaper retry for an object that stays
                lost, or mostly hidden.
            no_retry: objects not given ``features.retry_contrast_threshold``'s retry (nor are the ``quick`` ones).

        Raises:
            ImageError / CameraError: the image or calibration is unusable.
        """
        return estimate_image(self.objects, rgb, camera, obj_names, gt, frame_id, quick, no_retry)

    # -- batch call ------------------------------------------------------------------------------
    def estimate_frame(self, frame: Frame, obj_names: list[str], sequence: Sequence | None = None) -> list[PoseRecord]:
        """Estimate every object in a frame; never raises for bad input (failed records instead).

        With tracking on (``track.enabled`` and a renderer), a confident pose from the previous frame of
        ``sequence`` is followed into this one instead of being estimated afresh, and ``sequence`` is left
        holding what the next frame follows. Pass the same :class:`Sequence` with each frame of a sequence
        and a new one for unrelated frames; None: a new one (no memory of earlier frames).
        """
        sequence = Sequence() if sequence is None else sequence
        t0 = time.perf_counter()
        full, scale = frame, np.ones(2)
        replaced: Replaced = {}
        try:
            rgb = decode_image(frame)
            frame, rgb, scale = working_size(frame, rgb, self.conf.max_image_side_px)
            t_decode = time.perf_counter() - t0
            records = self._estimate(frame, rgb, obj_names, sequence, replaced)
        except Exception as e:  # a failure is a record, never a crash of the batch
            records = _failed(frame, obj_names, e)
            t_decode = time.perf_counter() - t0
        if any(r.status in FAILED for r in records):
            sequence.forget()  # a frame that could not be read breaks every track
        else:
            self._check_and_search(frame, full, rgb, records, sequence, replaced)
        if frame is not full:  # back to the full frame's pixels
            to_full_size(records, scale)
        for rec in records:
            rec.scene_id, rec.im_id, rec.stamp_ns = frame.scene_id, frame.im_id, frame.stamp_ns
            rec.obj_id = self.objects.obj_id(rec.obj_name, rec.obj_id)
            rec.timings["decode"] = t_decode
        return records

    def _estimate(
        self, frame: Frame, rgb: np.ndarray, obj_names: list[str], sequence: Sequence, replaced: Replaced
    ) -> list[PoseRecord]:
        """The frame's RGB estimate: tracked when tracking is on, else every object afresh."""
        if self.tracking():
            return estimate_tracked(self.objects, rgb, frame, obj_names, sequence, replaced)
        return estimate_image(self.objects, rgb, frame.camera, obj_names, frame.gt, frame.frame_id, replaced=replaced)

    def _check_and_search(
        self, frame: Frame, full: Frame, rgb: np.ndarray, records: list[PoseRecord], sequence: Sequence, replaced
    ) -> None:
        """The optional frame-level steps after the estimate: the weak-pose check, the verification score, one
        region for one object, depth alignment and search, the plane search (not where the depth search ran),
        the searches' poses' verification score. A bug in one leaves the poses as they were before it."""
        conf, objects = self.conf, self.objects
        searched = conf.depth.enabled and frame.has_depth
        steps = []
        if conf.verify_below > 0:
            steps.append(("verify_weak", lambda: verify_weak(objects, frame, rgb, records, replaced)))
        checked: dict[int, np.ndarray] = {}  # the poses scored, so the searches' new ones are scored after them
        verify = ("verify_poses", lambda: verify_poses(objects, frame, rgb, records, sequence, checked))
        was_ok: list[PoseRecord] = []  # the ok poses the verification score is first given

        def verify_first() -> None:
            was_ok[:] = [r for r in records if r.ok]
            verify_poses(objects, frame, rgb, records, sequence, checked)

        if conf.min_verification > 0:
            steps.append(("verify_poses", verify_first))
            if conf.retry_rejected:
                retried = functools.partial(self._retry_rejected, frame, rgb, records, sequence, checked, was_ok)
                steps.append(("retry_rejected", retried))
        if conf.region.max_overlap > 0:
            steps.append(("claim_regions", lambda: claim_regions(objects, frame, rgb, records, sequence)))
        if searched:
            steps.append(("use_depth", lambda: use_depth(objects, frame, full, rgb, records, sequence)))
        if conf.plane.enabled and not (searched and conf.depth.search):
            steps.append(("use_plane", lambda: use_plane(objects, frame, rgb, records, sequence)))
        if conf.min_verification > 0 and (searched or conf.plane.enabled):  # the searches' poses
            steps.append(verify)
        for name, step in steps:
            try:
                step()
            except Exception as e:  # a bug in an optional step must not cost the frame its RGB poses
                log.warning("%s: %s failed (%s: %s); poses as estimated before it", frame.frame_id, name,
                            type(e).__name__, e)  # fmt: skip
                log.debug("%s failed", name, exc_info=True)

    def _retry_rejected(
        self, frame: Frame, rgb: np.ndarray, records: list[PoseRecord], sequence: Sequence, checked, was_ok
    ) -> None:
        """``retry_rejected``: the retries for each object whose ok pose (among ``was_ok``, the ok poses before
        the score) the verification score rejected, and the score of what they find (``checked``: the poses
        :func:`verify_poses` scored).
        ``records`` changes only when all of it ran."""
        first = {r.obj_name: r for r in was_ok if not r.ok and has_retries(self.objects, r.obj_name)}
        if not first:
            return
        trial = list(records)
        retry_rejected(self.objects, rgb, frame.camera, frame.frame_id, frame.gt, trial, list(first))
        for rec in trial:
            old = first.get(rec.obj_name)
            if old is not None and rec is not old:
                rec.reason += f", after the verification score rejected the first pose ({old.verification:.2f})"
        verify_poses(self.objects, frame, rgb, trial, sequence, checked)
        records[:] = trial


def working_size(frame: Frame, rgb: np.ndarray, max_side_px: int) -> tuple[Frame, np.ndarray, np.ndarray]:
    """The frame and its pixels at the size it is estimated at (``max_image_side_px``), with the x and y
    scale factors; the frame itself when it is small enough."""
    cam, scale = working_camera(frame.camera, max_side_px)
    if cam is frame.camera:
        return frame, rgb, scale
    small = cv2.resize(rgb, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    return dataclasses.replace(frame, camera=cam), small, scale


def _failed(frame: Frame, obj_names: list[str], error: Exception) -> list[PoseRecord]:
    """Every object's record of a frame that could not be estimated: the status from the error's class
    (:func:`batchpose.method.records.failure_status`), its message as the reason."""
    if isinstance(error, BatchposeError):
        reason = str(error)
    else:  # an unexpected bug: the record names it, the debug log has the traceback
        log.debug("frame %s failed", frame.frame_id, exc_info=True)
        reason = f"{type(error).__name__}: {error}"
    return [PoseRecord(frame.frame_id, n, failure_status(error), reason) for n in obj_names]
