"""Binary glTF (GLB) of object meshes for Foxglove: export with the texture downscaled, and a GLB's bounds."""

from __future__ import annotations

import io
import struct
from typing import Any

import numpy as np

from batchpose.errors import DataError
from batchpose.io.files import one_line


def mesh_to_glb(mesh: Any, max_texture_px: int = 1024) -> bytes:
    """Binary glTF of a (textured) trimesh, with its texture downscaled to keep the MCAP small.

    Args:
        mesh: ``trimesh.Trimesh`` (or ``trimesh.Scene``) in metres, model frame.
        max_texture_px: longest texture side after downscaling (the YCB scans ship 4096²).

    Returns:
        GLB bytes; vertices stay in the model frame (glTF's Y-up is undone by the model pose that
        :func:`batchpose.io.mcap_poses.write_poses_mcap` gives Foxglove).
    """
    import trimesh
    from PIL import Image

    geoms = list(mesh.geometry.values()) if isinstance(mesh, trimesh.Scene) else [mesh]
    out = []
    for g in geoms:
        g = g.copy()
        mat = getattr(g.visual, "material", None)
        for attr in ("image", "baseColorTexture"):
            img = getattr(mat, attr, None)
            if img is None or max(img.size) <= max_texture_px:
                continue
            scale = max_texture_px / max(img.size)
            size = (max(1, round(img.size[0] * scale)), max(1, round(img.size[1] * scale)))
            small = img.resize(size, Image.Resampling.LANCZOS)
            if small.mode == "RGB":  # trimesh embeds JPEG-format images as JPEG (else PNG, 5x larger)
                buf = io.BytesIO()
                small.save(buf, format="JPEG", quality=90)
                small = Image.open(io.BytesIO(buf.getvalue()))
                small.load()
            setattr(mat, attr, small)
        out.append(g)
    scene = trimesh.Scene(out) if len(out) > 1 else out[0]
    return bytes(scene.export(file_type="glb"))


def glb_bounds(name: str, glb: bytes | bytearray) -> np.ndarray:
    """(2, 3) min/max corner of a GLB's geometry, metres.

    Raises:
        DataError: the bytes are not a GLB, or it has no geometry (naming the mesh ``name``).
    """
    import trimesh

    try:
        scene = trimesh.load(io.BytesIO(glb), file_type="glb")
    except (ValueError, KeyError, IndexError, TypeError, OSError, struct.error) as e:
        raise DataError(f"mesh {name!r}: cannot read the glb bytes ({one_line(e)})") from None
    b = np.asarray(scene.bounds, dtype=np.float64)
    if b.shape != (2, 3) or not np.all(np.isfinite(b)):
        raise DataError(f"mesh {name!r}: glb has no geometry")
    return b
