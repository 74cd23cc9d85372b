"""Binary little-endian PLY for triangle meshes: what Mitsuba and trimesh both read.

Vertices carry x, y, z, then nx, ny, nz when the mesh has normals, then u, v.
"""

from __future__ import annotations

import numpy as np

from nerfgauge.core.files import write_bytes_atomic


def ply_bytes(mesh) -> bytes:
    """Serialise a scenes.meshes.MeshData. Deterministic: same mesh, same bytes."""
    columns = [mesh.vertices]
    names = ["x", "y", "z"]
    if mesh.normals is not None:
        columns.append(mesh.normals)
        names += ["nx", "ny", "nz"]
    columns.append(mesh.uv)
    names += ["u", "v"]
    vertex_data = np.ascontiguousarray(np.concatenate(columns, axis=1), dtype="<f4")
    faces = np.asarray(mesh.faces, dtype="<i4")
    face_data = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face_data["n"], face_data["v"] = 3, faces
    header = ["ply", "format binary_little_endian 1.0", "comment nerfgauge ground-truth mesh, world coordinates",
              f"element vertex {len(vertex_data)}"]
    header += [f"property float {name}" for name in names]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + vertex_data.tobytes() + face_data.tobytes()


def write_ply(path, mesh) -> None:
    write_bytes_atomic(path, ply_bytes(mesh))
