"""Template library: content, caching (a second build renders nothing) and render failures."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from batchpose.config import EstimatorConfig, RenderConfig
from batchpose.io import library
from batchpose.method.render import get_renderer
from batchpose.stages import build_templates
from tests.conftest import K_SYN


class CountingRenderer:
    def __init__(self):
        self.calls = 0

    def render(self, *args, **kwargs):
        self.calls += 1
        return get_renderer().render(*args, **kwargs)


def test_library_points_lie_on_the_mesh(cracker_model, cracker_library):
    lib = cracker_library
    assert lib.n_views == 320 and len(lib.desc) == len(lib.pts3d) == len(lib.view_ids) > 5000
    # Every back-projected keypoint is on the surface: within 2 mm of a mesh vertex/face.
    surface, _ = trimesh.sample.sample_surface_even(cracker_model.mesh, 200_000, seed=0)
    dist, _ = cKDTree(surface).query(lib.pts3d[::50])
    assert np.percentile(dist, 95) < 0.002


def test_second_build_loads_and_renders_nothing(cracker_model, tmp_path):
    conf = EstimatorConfig(render=RenderConfig(n_views=12, image_fractions=(0.5,)))
    r1 = CountingRenderer()
    d1 = build_templates.build_library(cracker_model, conf, K_SYN, 640, 480, tmp_path, renderer=r1)
    assert r1.calls == 12
    assert {p.name for p in d1.iterdir()} == {"views.parquet", "templates.npz", "voxels.npz"}
    r2 = CountingRenderer()
    d2 = build_templates.build_library(cracker_model, conf, K_SYN, 640, 480, tmp_path, renderer=r2)
    assert d2 == d1 and r2.calls == 0
    lib = library.load(d2)
    assert lib.n_views == 12 and lib.views["n_keypoints"].sum() == len(lib.desc)
    # A different render config is a different library.
    conf2 = EstimatorConfig(render=RenderConfig(n_views=13, image_fractions=(0.5,)))
    d3 = build_templates.build_library(cracker_model, conf2, K_SYN, 640, 480, tmp_path, renderer=CountingRenderer())
    assert d3 != d1


def test_a_damaged_or_half_saved_library_is_built_again(cracker_model, tmp_path):
    """A cached library whose file is truncated is rendered again, not trusted; the half-saved copy a killed
    process left (NAME.tmp-PID, PID gone) is removed when the library is saved next."""
    conf = EstimatorConfig(render=RenderConfig(n_views=6, image_fractions=(0.5,)))
    d = build_templates.build_library(cracker_model, conf, K_SYN, 640, 480, tmp_path, renderer=CountingRenderer())
    (d / "templates.npz").write_bytes((d / "templates.npz").read_bytes()[:100])
    abandoned = d.with_name(d.name + ".tmp-999999999")  # no such process
    abandoned.mkdir()
    r = CountingRenderer()
    assert build_templates.build_library(cracker_model, conf, K_SYN, 640, 480, tmp_path, renderer=r) == d
    assert r.calls == 6 and library.load(d).n_views == 6 and not abandoned.exists()


def test_missing_gl_backend_names_the_package():
    code = (
        "from batchpose.errors import RenderError\n"
        "from batchpose.method.render import Renderer\n"
        "try:\n    Renderer()._context(64, 48)\nexcept RenderError as e:\n    print(e)\n"
    )
    env = dict(os.environ, PYOPENGL_PLATFORM="nosuchplatform")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=False)
    assert "PYOPENGL_PLATFORM=nosuchplatform" in r.stdout, r.stdout + r.stderr
    assert "libosmesa6" in r.stdout


def test_renderer_compiles_each_shader_program_once(cracker_model):
    """pyrender's own program cache misses on every render under OSMesa (its key holds a new ctypes object
    each time), so every render compiled and kept another program, 1-3 MB each: a worker's memory grew by
    ~0.7 MB a render. Ours keys by shaders and defines: flat and lit renders make two programs, however many."""
    from batchpose.method.render import Renderer  # noqa: PLC0415
    from batchpose.method.views import look_at  # noqa: PLC0415

    r = Renderer()
    T = look_at(cracker_model.center_m + np.array([0.5, 0.2, 0.3]), cracker_model.center_m, np.array([0, 0, 1.0]))
    filled = []
    for shading in ("flat", "flat", "lit", "flat", "lit"):
        _, depth = r.render(cracker_model.content_hash, cracker_model.mesh, T, K_SYN, 640, 480, shading)
        filled.append(int((depth > 0).sum()))
    programs = r._renderer._renderer._program_cache._program_cache
    r.close()
    assert len(programs) == 2
    assert filled[0] > 1000 and len(set(filled)) == 1


def test_a_render_does_not_depend_on_what_was_rendered_before(cracker_model):
    """Every mesh stays in the context's one scene, hidden unless rendered (so switching objects does not
    upload textures again): the cracker box after the gelatin box, and lit after flat, is pixel for pixel
    the cracker box in a fresh renderer."""
    from batchpose.config import MeshConfig  # noqa: PLC0415
    from batchpose.io.mesh import load_mesh  # noqa: PLC0415
    from batchpose.method.render import Renderer  # noqa: PLC0415
    from batchpose.method.views import look_at  # noqa: PLC0415
    from tests.conftest import GELATIN  # noqa: PLC0415

    gelatin = load_mesh(GELATIN, MeshConfig(), name="009_gelatin_box")
    T = look_at(cracker_model.center_m + np.array([0.4, 0.2, 0.3]), cracker_model.center_m, np.array([0, 0, 1.0]))
    fresh, switched = Renderer(), Renderer()
    for shading in ("flat", "lit"):
        want = fresh.render(cracker_model.content_hash, cracker_model.mesh, T, K_SYN, 640, 480, shading)
        other = switched.render(gelatin.content_hash, gelatin.mesh, T, K_SYN, 640, 480, "lit")
        got = switched.render(cracker_model.content_hash, cracker_model.mesh, T, K_SYN, 640, 480, shading)
        assert (other[1] > 0).sum() > 500  # the gelatin box was drawn in between
        assert (want[1] > 0).sum() > 1000
        assert np.array_equal(want[0], got[0]) and np.array_equal(want[1], got[1])
    fresh.close()
    switched.close()


def test_root_sift_descriptors_are_the_hellinger_map_of_sift_and_key_their_own_library(cracker_model):
    """RootSIFT (the default; ``paper`` keeps SIFT): each descriptor L1-normalised and square-rooted, so that
    Euclidean distance compares them by the Hellinger kernel; a library of one is never loaded for the other."""
    import dataclasses  # noqa: PLC0415

    from batchpose.method.features import detect  # noqa: PLC0415
    from batchpose.method.views import look_at  # noqa: PLC0415

    T = look_at(cracker_model.center_m + np.array([0.4, 0.2, 0.3]), cracker_model.center_m, np.array([0, 0, 1.0]))
    rgb, _ = get_renderer().render(cracker_model.content_hash, cracker_model.mesh, T, K_SYN, 640, 480, "lit")
    gray = rgb.mean(axis=2).astype(np.uint8)
    root = EstimatorConfig()
    sift = dataclasses.replace(root, features=dataclasses.replace(root.features, root_sift=False))
    assert root.features.root_sift
    xy_r, d_r = detect(gray, root.features)[:2]
    xy_s, d_s = detect(gray, sift.features)[:2]
    assert len(d_r) > 100 and np.array_equal(xy_r, xy_s)
    np.testing.assert_allclose(d_r, 512.0 * np.sqrt(d_s / d_s.sum(axis=1, keepdims=True)), rtol=1e-4, atol=1e-3)
    key = library.library_key
    assert key(cracker_model, root, K_SYN, 640, 480) != key(cracker_model, sift, K_SYN, 640, 480)


def test_query_only_feature_settings_share_one_library(cracker_model):
    """The retries' settings change how frames are searched, not the templates: one library for all of
    them, so trying ``--set features.retry_sigma=1.2`` renders nothing again; a template setting does."""
    import dataclasses  # noqa: PLC0415

    conf = EstimatorConfig()
    key = library.library_key

    def with_features(**kw) -> EstimatorConfig:
        return dataclasses.replace(conf, features=dataclasses.replace(conf.features, **kw))

    base = key(cracker_model, conf, K_SYN, 640, 480)
    assert key(cracker_model, with_features(retry_sigma=1.2), K_SYN, 640, 480) == base
    assert key(cracker_model, with_features(retry_contrast_threshold=0.0), K_SYN, 640, 480) == base
    assert key(cracker_model, with_features(contrast_threshold=0.03), K_SYN, 640, 480) != base


def test_the_retry_library_is_the_library_of_its_shading(cracker_model):
    """``render.retry_shading`` chooses a second library, not how the first is rendered: the first keeps its
    key, and the second is the very library a run with that shading first uses (one cache entry for both).
    "none", or the first library's shading, means no second library."""
    import dataclasses  # noqa: PLC0415

    conf = EstimatorConfig()
    key = library.library_key

    def with_render(**kw) -> EstimatorConfig:
        return dataclasses.replace(conf, render=dataclasses.replace(conf.render, **kw))

    flat, lit = with_render(shading="flat", retry_shading="none"), with_render(shading="lit", retry_shading="none")
    both = with_render(shading="flat", retry_shading="lit")
    assert key(cracker_model, both, K_SYN, 640, 480) == key(cracker_model, flat, K_SYN, 640, 480)
    second = library.retry_library_conf(both)
    assert second is not None
    assert key(cracker_model, second, K_SYN, 640, 480) == key(cracker_model, lit, K_SYN, 640, 480)
    assert key(cracker_model, flat, K_SYN, 640, 480) != key(cracker_model, lit, K_SYN, 640, 480)
    assert library.retry_library_conf(flat) is None
    assert library.retry_library_conf(with_render(shading="lit", retry_shading="lit")) is None


def test_a_light_from_above_brightens_the_upper_half():
    """``light_from`` puts the lit render's light where it says (camera axes, y down): a sphere lit from above
    the camera is brighter in its upper half, lit from below in its lower half; without it (a headlight) the
    two halves match."""
    from batchpose.method.render import Renderer  # noqa: PLC0415

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    T = np.eye(4)
    T[2, 3] = 1.0
    r = Renderer()
    halves = {}
    for name, light in (("above", np.array([0.0, -1.0, -0.3])), ("below", np.array([0.0, 1.0, -0.3])), ("head", None)):
        rgb, depth = r.render("sphere", sphere, T, K_SYN, 640, 480, "lit", light_from=light)
        grey = rgb.astype(float).mean(axis=2)
        on = depth > 0
        rows = np.nonzero(on.any(axis=1))[0]
        middle = (rows.min() + rows.max()) // 2
        upper, lower = grey[: middle - 5][on[: middle - 5]].mean(), grey[middle + 5 :][on[middle + 5 :]].mean()
        halves[name] = (upper, lower)
    r.close()
    assert halves["above"][0] > 1.25 * halves["above"][1]
    assert halves["below"][1] > 1.25 * halves["below"][0]
    assert abs(halves["head"][0] - halves["head"][1]) < 0.05 * halves["head"][0]
