"""Triangle meshes of the procedural shapes, with exact normals and uv in scene units.

The generator renders every non-sphere shape from exactly these triangles and writes
them as the dataset's ground-truth meshes, so rendered and ground-truth geometry agree.
uv is in scene units (a texture period of 0.5 means 0.5 scene units on the surface).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass(frozen=True, eq=False)
class MeshData:
    """vertices [V, 3], faces [F, 3] int, normals [V, 3] unit or None (flat shading),
    uv [V, 2] in scene units (float64; a user asset's texture coordinates instead),
    colors [V, 3] linear RGB per vertex or None."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: Optional[np.ndarray]
    uv: np.ndarray
    colors: Optional[np.ndarray] = None

    def __post_init__(self):
        v, f = np.asarray(self.vertices), np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"mesh needs vertices [V,3] and faces [F,3], got {v.shape}, {f.shape}")
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError("mesh faces index vertices that do not exist")

    def transformed(self, matrix: np.ndarray) -> "MeshData":
        """Apply a 4x4 rigid transform (rotation + translation) to points and normals."""
        rot, shift = matrix[:3, :3], matrix[:3, 3]
        normals = None if self.normals is None else self.normals @ rot.T
        return MeshData(self.vertices @ rot.T + shift, self.faces, normals, self.uv, self.colors)

    def scaled(self, scale: float, shift) -> "MeshData":
        """Points mapped to scale * p + shift (uniform scale > 0: normals unchanged)."""
        return MeshData(self.vertices * scale + np.asarray(shift, np.float64), self.faces, self.normals, self.uv,
                        self.colors)

    def subset(self, keep_faces: np.ndarray) -> "MeshData":
        """The faces selected by the boolean mask [F], without the vertices none of them uses."""
        used, faces = np.unique(self.faces[keep_faces], return_inverse=True)
        pick = (lambda a: None if a is None else a[used])
        return MeshData(self.vertices[used], faces.reshape(-1, 3), pick(self.normals), self.uv[used],
                        pick(self.colors))

    def bounds(self) -> np.ndarray:
        """[2, 3] min and max corner."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    def to_trimesh(self) -> "trimesh.Trimesh":
        import trimesh  # trimesh: 1.4 s with scipy and networkx, only when used (see `icosphere`)

        return trimesh.Trimesh(self.vertices, self.faces, vertex_normals=self.normals,
                               process=False)


def rotation_matrix(degrees_xyz) -> np.ndarray:
    """R = Rz @ Ry @ Rx for Euler angles in degrees. Returns [3, 3]."""
    ax, ay, az = (math.radians(a) for a in degrees_xyz)
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def pose(center, degrees_xyz) -> np.ndarray:
    """Local-to-world 4x4: rotate by Euler angles, then move to `center`."""
    matrix = np.eye(4)
    matrix[:3, :3] = rotation_matrix(degrees_xyz)
    matrix[:3, 3] = center
    return matrix


def icosphere(center, radius, subdivisions: int = 4) -> MeshData:
    """Geodesic sphere; its vertices lie on the true sphere (chord error ~ 5e-4 radius)."""
    # trimesh (with scipy and networkx) takes 1.4 s to import: here rather than at the top,
    # so that every `nerfgauge` command (which imports the scene recipes) does not pay it
    # before it parses its arguments; a command that builds meshes pays it once.
    import trimesh  # trimesh: only when a sphere is built

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    unit = np.asarray(ico.vertices, np.float64)
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    uv = np.stack([np.arctan2(unit[:, 1], unit[:, 0]) * radius, np.arccos(np.clip(unit[:, 2], -1, 1)) * radius], 1)
    return MeshData(unit * radius + np.asarray(center, np.float64), np.asarray(ico.faces), unit, uv)


def box(size) -> MeshData:
    """Axis-aligned box centred at the origin: 4 own vertices per face, flat normals."""
    half = np.asarray(size, np.float64) / 2
    vertices, normals, uv, faces = [], [], [], []
    for axis in range(3):
        u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
        for sign in (-1.0, 1.0):
            corners = []
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[u_axis], p[v_axis] = sign * half[axis], a * half[u_axis], b * half[v_axis]
                corners.append(p)
            n = np.zeros(3)
            n[axis] = sign
            base = len(vertices)
            vertices += corners
            normals += [n] * 4
            uv += [(p[u_axis] + half[u_axis], p[v_axis] + half[v_axis]) for p in corners]
            quad = [(0, 1, 2), (0, 2, 3)] if sign > 0 else [(0, 2, 1), (0, 3, 2)]
            faces += [tuple(base + i for i in tri) for tri in quad]
    return MeshData(np.array(vertices), np.array(faces), np.array(normals), np.array(uv))


def capped_cylinder(radius, height, segments: int = 96) -> MeshData:
    """Cylinder around +Z from -height/2 to +height/2 with flat caps; smooth side normals."""
    angle = np.linspace(0, 2 * math.pi, segments + 1)  # seam vertex repeated for uv
    ring = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], 1)  # [S+1, 3]
    z = np.array([0, 0, height / 2])
    side_v = np.concatenate([ring * radius - z, ring * radius + z])
    side_n = np.concatenate([ring, ring])
    side_uv = np.concatenate([np.stack([angle * radius, np.zeros_like(angle)], 1),
                              np.stack([angle * radius, np.full_like(angle, height)], 1)])
    n1 = segments + 1
    i = np.arange(segments)
    side_f = np.concatenate([np.stack([i, i + 1, i + 1 + n1], 1), np.stack([i, i + 1 + n1, i + n1], 1)])
    parts = [(side_v, side_f, side_n, side_uv)]
    for sign in (-1.0, 1.0):
        centre = np.array([[0, 0, sign * height / 2]])
        rim = ring[:-1] * radius + centre
        verts = np.concatenate([centre, rim])
        normal = np.tile([0, 0, sign], (len(verts), 1))
        j = np.arange(segments)
        fan = np.stack([np.zeros_like(j), 1 + j, 1 + (j + 1) % segments], 1)
        if sign < 0:
            fan = fan[:, [0, 2, 1]]
        parts.append((verts, fan, normal, verts[:, :2] + radius))
    return _concatenate(parts)


def torus(major, minor, major_segments: int = 96, minor_segments: int = 48) -> MeshData:
    """Torus around +Z with analytic normals; uv = arc lengths along ring and tube."""
    a = np.linspace(0, 2 * math.pi, major_segments + 1)[:, None]  # [M+1, 1]
    b = np.linspace(0, 2 * math.pi, minor_segments + 1)[None, :]  # [1, N+1]
    normal = np.stack([np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), np.broadcast_to(np.sin(b), (a.size, b.size))], -1)
    centre = np.stack([np.cos(a) * major, np.sin(a) * major, np.zeros_like(a)], -1)  # [M+1, 1, 3]
    vertices = centre + minor * normal
    uv = np.stack(np.broadcast_arrays(a * major, b * minor), -1)
    cols = minor_segments + 1
    i, j = np.meshgrid(np.arange(major_segments), np.arange(minor_segments), indexing="ij")
    v00, v10, v01, v11 = i * cols + j, (i + 1) * cols + j, i * cols + j + 1, (i + 1) * cols + j + 1
    faces = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)])
    return MeshData(vertices.reshape(-1, 3), faces, normal.reshape(-1, 3), uv.reshape(-1, 2))


def _concatenate(parts) -> MeshData:
    vertices, faces, normals, uvs, offset = [], [], [], [], 0
    for v, f, n, uv in parts:
        vertices.append(v), faces.append(f + offset), normals.append(n), uvs.append(uv)
        offset += len(v)
    return MeshData(*(np.concatenate(x) for x in (vertices, faces, normals, uvs)))
