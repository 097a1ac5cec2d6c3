"""load_mesh's cache: a cached mesh renders exactly as the parsed one, is not parsed again, and is never
reused for other files or settings; a damaged entry is replaced."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import trimesh

from batchpose.config import MeshConfig
from batchpose.errors import MeshError
from batchpose.io import mesh as mesh_module
from batchpose.io.mesh import load_mesh
from batchpose.method.render import get_renderer
from tests.conftest import GELATIN, K_SYN


def _entries(cache):
    return sorted((cache / "meshes").glob("*.pkl"))


def _render(model):
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.4]
    return get_renderer().render(model.content_hash, model.mesh, T, K_SYN, 320, 240, "flat", 0.01, 20.0)


def _no_parsing(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the mesh file was parsed again")

    monkeypatch.setattr(trimesh, "load", refuse)


def test_cached_mesh_is_the_parsed_one_and_not_parsed_again(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    parsed = load_mesh(GELATIN, cache_dir=cache)
    assert len(_entries(cache)) == 1
    _no_parsing(monkeypatch)
    cached = load_mesh(GELATIN, cache_dir=cache, name="another name")
    assert cached.name == "another name" and cached.path == GELATIN
    assert cached.content_hash == parsed.content_hash and cached.diameter_m == parsed.diameter_m
    np.testing.assert_array_equal(cached.mesh.vertices, parsed.mesh.vertices)
    np.testing.assert_array_equal(cached.mesh.faces, parsed.mesh.faces)
    (rgb_p, depth_p), (rgb_c, depth_c) = _render(parsed), _render(cached)
    assert (depth_p > 0).sum() > 1000
    np.testing.assert_array_equal(rgb_c, rgb_p)
    np.testing.assert_array_equal(depth_c, depth_p)


def test_other_settings_or_files_are_not_served_from_the_cache(tmp_path):
    cache = tmp_path / "cache"
    load_mesh(GELATIN, cache_dir=cache)
    small = load_mesh(GELATIN, MeshConfig(max_texture_px=64), cache_dir=cache)
    assert max(small.mesh.visual.material.image.size) == 64
    assert len(_entries(cache)) == 2
    # The same files with another texture: another key.
    copy = tmp_path / "copy"
    shutil.copytree(GELATIN.parent, copy)
    tex = next(p for p in copy.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    tex.write_bytes(tex.read_bytes() + b"\0")
    other = load_mesh(copy / GELATIN.name, cache_dir=cache)
    assert other.content_hash != small.content_hash
    assert len(_entries(cache)) == 3


@pytest.mark.parametrize("damage", ["truncated", "flipped byte"])
def test_damaged_entry_is_replaced(tmp_path, caplog, damage):
    cache = tmp_path / "cache"
    first = load_mesh(GELATIN, cache_dir=cache)
    (entry,) = _entries(cache)
    data = bytearray(entry.read_bytes())
    if damage == "truncated":
        data = data[:1000]
    else:
        data[len(data) // 2] ^= 0x01  # e.g. in the vertex array: would unpickle without complaint
    entry.write_bytes(bytes(data))
    again = load_mesh(GELATIN, cache_dir=cache)
    assert "damaged cached mesh" in caplog.text
    np.testing.assert_array_equal(again.mesh.vertices, first.mesh.vertices)
    assert entry.stat().st_size == len(entry.read_bytes()) > 1000  # rewritten whole
    assert load_mesh(GELATIN, cache_dir=cache).content_hash == first.content_hash
    assert not list((cache / "meshes").glob("*.tmp"))


def test_millimetre_mesh_cached_with_its_scale_and_still_refused(tmp_path, caplog, monkeypatch):
    src = load_mesh(GELATIN).mesh.copy()
    src.apply_scale(1000.0)
    p = tmp_path / "gelatin_mm.ply"
    src.export(p)
    cache = tmp_path / "cache"
    load_mesh(p, cache_dir=cache)
    caplog.clear()
    _no_parsing(monkeypatch)
    assert load_mesh(p, cache_dir=cache).scale == 0.001 and "millimetres" not in caplog.text  # once per run
    monkeypatch.setattr(mesh_module, "_WARNED", set())  # another run (process) loading it from the cache
    m = load_mesh(p, cache_dir=cache)
    assert m.scale == 0.001 and 0.05 < m.diameter_m < 0.2
    assert "millimetres" in caplog.text  # warned again, not silently scaled
    with pytest.raises(MeshError, match="looks like millimetres"):
        monkeypatch.undo()
        load_mesh(p, MeshConfig(on_millimetres="refuse"), cache_dir=cache)


def test_unwritable_cache_only_costs_time(tmp_path):
    blocker = tmp_path / "cache"
    blocker.mkdir()
    (blocker / "meshes").write_text("a file where the folder should be")
    m = load_mesh(GELATIN, cache_dir=blocker)
    assert m.diameter_m > 0.05
