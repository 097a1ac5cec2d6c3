"""Load a textured mesh (OBJ+MTL+texture, PLY with texture or vertex colours) in metres."""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import pickle
import re
import tempfile
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image
from trimesh.visual import ColorVisuals, TextureVisuals

from batchpose.config import MeshConfig
from batchpose.core.model import ObjectModel, diameter
from batchpose.errors import MeshError

log = logging.getLogger("batchpose")

_REF_RE = re.compile(rb"^\s*(?:mtllib|map_Kd|map_Ka)\s+(.+?)\s*$", re.MULTILINE)

#: Bump when what :func:`load_mesh` makes of a file changes, so cached meshes are not reused.
MESH_CACHE_FORMAT = 2  # 2: ObjectModel moved to batchpose.core.model (pickled by module path)


def _referenced_files(path: Path) -> list[Path]:
    """The mesh file plus the MTL and texture files it references (for content hashing)."""
    out, todo, seen = [], [path], set()
    while todo:
        p = todo.pop()
        if p in seen or not p.is_file():
            continue
        seen.add(p)
        out.append(p)
        if p.suffix.lower() in (".obj", ".mtl"):
            for m in _REF_RE.finditer(p.read_bytes()):
                todo.append(p.parent / m.group(1).decode(errors="replace"))
    return sorted(out)


def content_hash(path: Path) -> str:
    h = hashlib.sha256()
    for p in _referenced_files(path):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def _limit_texture(mesh: trimesh.Trimesh, max_px: int) -> None:
    """Downscale the mesh's texture image in place so its longer side is at most ``max_px``."""
    visual = mesh.visual
    if max_px <= 0 or not isinstance(visual, TextureVisuals):  # the only visual of kind "texture"
        return
    mat = visual.material
    for attr in ("image", "baseColorTexture"):
        img = getattr(mat, attr, None)
        if img is not None and hasattr(img, "size") and max(img.size) > max_px:
            scale = max_px / max(img.size)
            size = (max(1, round(img.size[0] * scale)), max(1, round(img.size[1] * scale)))
            setattr(mat, attr, img.resize(size, Image.Resampling.LANCZOS))


#: Warnings already given by this process: a mesh is loaded by the run, its workers' setup and the report,
#: and the user is told about its units once.
_WARNED: set[str] = set()


def _warn_once(path: Path, message: str) -> None:
    """Warn ``path: message`` unless this process has warned about that mesh file already."""
    if str(Path(path)) not in _WARNED:
        _WARNED.add(str(Path(path)))
        log.warning("%s: %s", path, message)


def quiet_mesh_warnings(paths) -> None:
    """Treat the unit warnings of the meshes at ``paths`` as given (in a worker: the run gave them)."""
    _WARNED.update(str(Path(p)) for p in paths)


def unit_scale(path: Path, bounds: np.ndarray, conf: MeshConfig = MeshConfig()) -> float:
    """Factor that brings a mesh file's coordinates to metres: the units rule of :func:`load_mesh`.

    Scorers that read a run's meshes without texture (model points for ADD / ADD-S) call this so that they
    scale a mesh exactly as the estimator did.

    Args:
        path: the mesh file (named in the warning and the error).
        bounds: (2, 3) [min, max] corners of the mesh's bounding box, file units (``trimesh.Trimesh.bounds``).
        conf: ``units``, ``on_millimetres`` and ``mm_diagonal_threshold`` are used.

    Returns:
        1.0, or 0.001 for a millimetre mesh (``units: mm``, or ``auto`` with a diagonal above the threshold).

    Raises:
        MeshError: a millimetre mesh under ``units: auto`` with ``on_millimetres: refuse``.
    """
    bounds = np.asarray(bounds, dtype=np.float64)
    if bounds.shape != (2, 3):
        raise ValueError(f"bounds must have shape (2, 3), got {bounds.shape}")
    diag = float(np.linalg.norm(bounds[1] - bounds[0]))
    units = conf.units
    if units == "auto" and diag > conf.mm_diagonal_threshold:
        if conf.on_millimetres == "refuse":
            raise MeshError(
                f"{path}: bounding-box diagonal is {diag:.1f} units, so the mesh looks like millimetres; "
                "convert it to metres or set mesh.on_millimetres: convert"
            )
        _warn_once(path, f"bounding-box diagonal {diag:.1f} looks like millimetres; scaling by 0.001")
        units = "mm"
    return 0.001 if units == "mm" else 1.0


def load_mesh(
    path: Path, conf: MeshConfig = MeshConfig(), name: str | None = None, cache_dir: Path | None = None
) -> ObjectModel:
    """Load a textured mesh and bring it to metres.

    With ``cache_dir``, the loaded mesh (texture already downscaled) is kept in ``cache_dir/meshes`` under
    a key of the files' content and the mesh settings, and later loads of the same files read it from there
    (~50 ms instead of ~0.7 s of OBJ parsing, JPEG decoding and resampling for a YCB mesh; every worker of a
    run loads every mesh). The cached mesh is the parsed one, so renders are identical. An unreadable cache
    entry is replaced; a cache folder that cannot be written only costs the time. Entries are Python
    pickles (checksummed against damage, not against a deliberate forgery): like any pickle cache, the
    folder must not be writable by people you would not let run code as you.

    Raises:
        MeshError: missing or unreadable file, no faces, no texture/vertex colours, or a millimetre mesh
            with ``on_millimetres: refuse``.
    """
    path = Path(path)
    name = name or path.parent.name or path.stem
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")
    digest = content_hash(path)
    if cache_dir is None:
        return _parse_mesh(path, conf, name, digest)
    entry = Path(cache_dir) / "meshes" / f"{_cache_key(digest, conf)[:32]}.pkl"  # the content's, whatever its name
    cached = _read_cached(entry, digest)
    if cached is not None:
        if cached.scale != 1.0 and conf.units == "auto":  # as the first load warned
            _warn_once(path, f"bounding-box diagonal looks like millimetres; scaling by {cached.scale:g}")
        return dataclasses.replace(cached, name=name, path=path)
    model = _parse_mesh(path, conf, name, digest)
    _write_cached(entry, model)
    return model


def _cache_key(digest: str, conf: MeshConfig) -> str:
    """What a cached mesh depends on: the files, the settings that change the loaded mesh, the libraries."""
    from PIL import __version__ as pil_version  # noqa: PLC0415

    parts = (
        MESH_CACHE_FORMAT,
        digest,
        conf.units,
        conf.on_millimetres,
        conf.mm_diagonal_threshold,
        conf.max_texture_px,
        trimesh.__version__,
        pil_version,
    )
    return hashlib.sha256(repr(parts).encode()).hexdigest()


_MAGIC = b"batchpose mesh\n"


def _read_cached(entry: Path, digest: str) -> ObjectModel | None:
    """The model in ``entry``, or None when there is none, it cannot be read (a cache folder that is not
    one) or it is damaged (then it is removed). An entry is the magic line, the SHA-256 of the pickle and
    the pickle: a damaged byte is found before anything is unpickled."""
    try:
        data = entry.read_bytes()
    except OSError as e:
        if not isinstance(e, FileNotFoundError):
            log.debug("%s: cached mesh not readable (%s)", entry, e)
        return None
    head, body = data[: len(_MAGIC) + 32], data[len(_MAGIC) + 32 :]
    model, why = None, "damaged cached mesh"
    if head[: len(_MAGIC)] == _MAGIC and hashlib.sha256(body).digest() == head[len(_MAGIC) :]:
        try:
            model = pickle.loads(body)  # our own entry, checked above
        except Exception as e:  # pickled by an incompatible version of a library
            why = f"unreadable cached mesh ({type(e).__name__})"
        else:
            why = "cached mesh does not match its key"
    if isinstance(model, ObjectModel) and model.content_hash == digest:
        return model
    log.warning("%s: %s; loading the mesh file again", entry, why)
    try:
        entry.unlink(missing_ok=True)
    except OSError:
        pass
    return None


def _write_cached(entry: Path, model: ObjectModel) -> None:
    """Keep ``model`` in ``entry`` (atomically: a killed run leaves no partial entry)."""
    body = pickle.dumps(model, protocol=pickle.HIGHEST_PROTOCOL)
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=entry.parent, prefix=entry.name, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(_MAGIC + hashlib.sha256(body).digest())
                f.write(body)
            os.chmod(tmp, 0o644)  # as the template libraries beside it (mkstemp makes 0600)
            os.replace(tmp, entry)
        finally:
            Path(tmp).unlink(missing_ok=True)
    except OSError as e:
        log.debug("%s: mesh not cached (%s)", entry, e)


def _parse_mesh(path: Path, conf: MeshConfig, name: str, digest: str) -> ObjectModel:
    """:func:`load_mesh` without the cache."""
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for corrupt files
        # (an ImportError: trimesh guessing the text encoding of bytes that are not text)
        msg = "undecodable bytes" if isinstance(e, ImportError) else (str(e).splitlines() or [type(e).__name__])[0]
        kind = path.suffix.lstrip(".").upper() or "mesh"
        raise MeshError(f"{path}: cannot read mesh: not a valid {kind} file ({msg})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise MeshError(f"{path}: mesh has no faces")
    # trimesh's visuals: TextureVisuals (kind "texture") or ColorVisuals (kind "vertex", "face" or None)
    visual = loaded.visual
    has_texture = isinstance(visual, TextureVisuals) and (
        (getattr(visual, "uv", None) is not None and getattr(visual.material, "image", None) is not None)
        or getattr(visual.material, "baseColorTexture", None) is not None
    )
    if isinstance(visual, ColorVisuals) and visual.kind == "vertex":
        cols = np.asarray(visual.vertex_colors)[:, :3]
        has_texture = cols.size > 0 and float(cols.std()) > 0.0
    if not has_texture:
        raise MeshError(
            f"{path}: mesh has no texture or vertex colours (SIFT needs a textured mesh; "
            "check that the .mtl and texture image sit beside the .obj)"
        )
    scale = unit_scale(path, loaded.bounds, conf)
    if scale != 1.0:
        loaded.apply_scale(scale)
    _limit_texture(loaded, conf.max_texture_px)
    if not np.all(np.isfinite(loaded.vertices)):
        raise MeshError(f"{path}: mesh has NaN or infinite vertex coordinates")
    return ObjectModel(
        name=name,
        path=path,
        mesh=loaded,
        diameter_m=diameter(loaded.vertices),
        content_hash=digest,
        scale=scale,
    )
