"""A template library's descriptor index kept in its folder: loaded, it answers exactly as a built one;
damaged or half-written, it is built again; an unwritable folder only costs the build."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from batchpose.config import MatchConfig
from batchpose.io import library as lib_io
from batchpose.method import correspondences
from batchpose.method.correspondences import flann_index, knn

CONF = MatchConfig()


@pytest.fixture()
def library(cracker_library, tmp_path):
    """The cracker box's library in a folder of this test's own."""
    folder = tmp_path / "lib"
    shutil.copytree(cracker_library.folder, folder, ignore=shutil.ignore_patterns("flann-*"))
    return lib_io.load(folder)


def _queries(lib) -> np.ndarray:
    rng = np.random.default_rng(0)
    q = lib.desc[rng.integers(0, len(lib.desc), 500)]
    return (q + rng.normal(0.0, 0.02, q.shape)).astype(np.float32)


def _kept(folder):
    return sorted(p.name for p in folder.glob("flann-*"))


def _no_building(monkeypatch):
    def refuse(seed=0):
        raise AssertionError("the index was built again")

    monkeypatch.setattr(correspondences, "seed_c_rand", refuse)


def test_kept_index_answers_as_a_built_one(library, monkeypatch):
    q = _queries(library)
    fresh = knn(flann_index(library.desc, CONF), q, 4, CONF)
    flann_index(library.desc, CONF, keep_in=library.folder)
    kept = _kept(library.folder)
    assert len(kept) == 2 and kept[1] == kept[0] + ".sha256"
    _no_building(monkeypatch)
    loaded = knn(flann_index(library.desc, CONF, keep_in=library.folder), q, 4, CONF)
    np.testing.assert_array_equal(loaded[0], fresh[0])
    np.testing.assert_array_equal(loaded[1], fresh[1])
    assert fresh[0][:, 0].size == 500 and (fresh[1][:, 0] < fresh[1][:, 1]).mean() > 0.5  # a real search


def test_other_trees_get_their_own_index(library):
    flann_index(library.desc, CONF, keep_in=library.folder)
    flann_index(library.desc, MatchConfig(flann_trees=CONF.flann_trees + 1), keep_in=library.folder)
    assert len(_kept(library.folder)) == 4


@pytest.mark.parametrize("damage", ["flipped byte", "no check file"])
def test_damaged_or_half_written_index_is_built_again(library, caplog, damage):
    q = _queries(library)
    fresh = knn(flann_index(library.desc, CONF), q, 2, CONF)
    flann_index(library.desc, CONF, keep_in=library.folder)
    index_file = next(library.folder.glob("flann-*.idx"))
    check_file = index_file.with_name(index_file.name + ".sha256")
    if damage == "flipped byte":
        data = bytearray(index_file.read_bytes())
        data[len(data) // 2] ^= 0x10
        index_file.write_bytes(bytes(data))
    else:
        check_file.unlink()  # killed between writing the index and its check file
    again = knn(flann_index(library.desc, CONF, keep_in=library.folder), q, 2, CONF)
    np.testing.assert_array_equal(again[0], fresh[0])
    if damage == "flipped byte":
        assert "does not match its check file" in caplog.text
    assert check_file.is_file()  # written again, whole
    assert correspondences._load_index(index_file, np.ascontiguousarray(library.desc)) is not None
    assert not list(library.folder.glob("*.tmp*"))


def test_unwritable_folder_only_costs_the_build(library, tmp_path):
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("x")
    index = flann_index(library.desc, CONF, keep_in=not_a_folder)
    idx, _ = knn(index, _queries(library), 1, CONF)
    assert idx.shape == (500, 1)
