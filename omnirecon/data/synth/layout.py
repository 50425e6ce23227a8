"""Scene composition: which primitives, where, on what ground, seen by which cameras, under which light.

World frame: z up, ground plane ``z = 0``. Objects rest on the ground (a few float a little above
it) at random orientations; their footprints (the circles bounding their vertices seen from
above) never overlap, so objects never interpenetrate. Everything is drawn from one
``numpy.random.Generator`` seeded by the scene seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from omnirecon.data.synth import rigs
from omnirecon.data.synth.primitives import KINDS, Primitive, primitive_mesh, random_params
from omnirecon.data.synth.render import Lighting
from omnirecon.data.synth.textures import random_color, random_texture

GROUND_ID = 255
"""Label id of the ground (and, in forward scenes, the backdrop wall)."""


@dataclass
class Layout:
    """Everything that defines a scene before rendering."""

    primitives: list[Primitive]
    local_meshes: list  # trimesh.Trimesh per primitive, local frame
    c2w: np.ndarray
    """OpenCV camera-to-world per view. ``# [V, 4, 4]``"""
    fov: float
    """Horizontal field of view, radians."""
    light: Lighting
    background: list[float]
    rig: str
    """``"object"``, ``"frontal"`` or ``"forward"``."""
    ground_vertices: np.ndarray | None = None
    """Ground (and wall) quads as triangles, world frame. ``# [G, 3]``"""
    ground_faces: np.ndarray | None = None
    """``# [Gf, 3]``"""
    ground_texture: dict | None = None
    ground_tile: float = 1.0
    extras: dict = field(default_factory=dict)
    """Rig parameters for ``scene.json``."""


def make_layout(rng: np.random.Generator, rig: str, views: int, ground: bool, objects: tuple[int, int],
                detail: int = 1) -> Layout:
    """Draw a random scene for ``rig`` with ``views`` cameras."""
    n = int(rng.integers(objects[0], objects[1] + 1))
    if rig == "forward":
        return _forward_layout(rng, n, views, ground, detail)
    return _object_layout(rng, n, views, ground, detail, rig)


# ---------------------------------------------------------------------- object-centric rigs
def _object_layout(rng, n: int, views: int, ground: bool, detail: int, rig: str) -> Layout:
    shapes = [_random_shape(rng, rng.uniform(0.22, 0.45), detail) for _ in range(n)]
    radius = 0.6

    def sample(r: float, tries: int) -> np.ndarray:
        rho = max(radius * 1.1 ** (tries // 10) - r, 0.0)  # widen the area while the objects do not fit
        return rho * math.sqrt(rng.uniform()) * _unit2(rng)

    prims, meshes = _place(rng, shapes, sample, lambda *_: True, float_prob=0.2 if ground else 1.0)
    verts = np.concatenate([_world_pose(p.pose, m.vertices) for p, m in zip(prims, meshes)])
    centre = (verts.min(0) + verts.max(0)) / 2
    content_radius = float(np.linalg.norm(verts - centre, axis=1).max())
    fov = math.radians(rng.uniform(35, 55))
    distance = rigs.fit_distance(content_radius, fov, margin=rng.uniform(1.05, 1.25))
    if rig == "frontal":
        c2w = rigs.frontal_arc(centre, distance, views, rng, elevation=(10.0, 45.0) if ground else (-30.0, 45.0))
    else:
        c2w = rigs.sphere_band(centre, distance, views, (10.0, 65.0) if ground else (-60.0, 65.0), rng)
    layout = Layout(prims, meshes, c2w, fov, _light(rng, forward=False), _background(rng), rig,
                    extras={"distance": distance, "target": centre.tolist(), "content_radius": content_radius})
    if ground:
        # A square patch whose corners stay within 0.9 x the camera distance of the look-at
        # centre: then every ground point is in front of every camera (camera z >= 0.1 d).
        half = math.sqrt(max((0.9 * distance) ** 2 - centre[2] ** 2, 0.0) / 2)
        c = np.array([centre[0], centre[1], 0.0])
        corners = c + np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]])
        _add_ground(layout, rng, [corners], tile=rng.uniform(0.8, 2.0))
    return layout


# ---------------------------------------------------------------------- forward-facing rig
def _forward_layout(rng, n: int, views: int, ground: bool, detail: int) -> Layout:
    fov = math.radians(rng.uniform(50, 65))
    height = rng.uniform(0.6, 1.0)
    pitch = math.radians(rng.uniform(6, 16))
    direction = np.array([0.0, math.cos(pitch), -math.sin(pitch)])
    origin = np.array([0.0, 0.0, height])
    extent = rng.uniform(0.12, 0.22)
    c2w = rigs.forward_grid(origin, direction, views, extent, rng)
    near_y, far_y = 1.8, 5.0
    shapes = [_random_shape(rng, rng.uniform(0.25, 0.6), detail) for _ in range(n)]
    K = rigs.intrinsics(fov, 100, 100)
    w2c = np.linalg.inv(c2w)

    def sample(r: float, tries: int) -> np.ndarray:
        y = rng.uniform(near_y, far_y)
        half = max(y * math.tan(fov / 2) * 0.8 - r, 0.0)
        return np.array([rng.uniform(-half, half), y])

    def framed(world: np.ndarray) -> bool:  # inside every view with a 3 % border
        cam = world @ w2c[:, :3, :3].transpose(0, 2, 1) + w2c[:, None, :3, 3]  # [V, P, 3]
        if cam[..., 2].min() < 0.2:
            return False
        uv = cam[..., :2] / cam[..., 2:] * K[0, 0] + K[0, 2]
        return bool((uv > 3).all() and (uv < 97).all())

    prims, meshes = _place(rng, shapes, sample, framed, float_prob=0.2 if ground else 0.6)
    layout = Layout(prims, meshes, c2w, fov, _light(rng, forward=True), _background(rng), "forward",
                    extras={"height": height, "pitch_deg": math.degrees(pitch), "grid_extent": extent})
    if ground:
        back = far_y + 1.5
        half_x = back * math.tan(fov / 2) * 1.6 + extent
        top = height + back * math.tan(fov / 2 + pitch) * 1.3
        floor = np.array([[-half_x, 0.3, 0], [half_x, 0.3, 0], [half_x, back, 0], [-half_x, back, 0]])
        wall = np.array([[-half_x, back, 0], [half_x, back, 0], [half_x, back, top], [-half_x, back, top]])
        _add_ground(layout, rng, [floor, wall], tile=rng.uniform(1.0, 2.5))
    return layout


# ---------------------------------------------------------------------- shared pieces
def _random_shape(rng, size: float, detail: int) -> tuple[str, dict, object, np.ndarray]:
    """A primitive kind, its parameters, its local mesh and a random rotation."""
    kind = KINDS[rng.integers(len(KINDS))]
    params = random_params(kind, size, rng)
    rotation = Rotation.from_quat(rng.standard_normal(4)).as_matrix()
    return kind, params, primitive_mesh(kind, params, detail), rotation


def _place(rng, shapes, sample, accept, float_prob: float) -> tuple[list[Primitive], list]:
    """Put shapes on the ground with non-overlapping footprints.

    ``sample(r, tries) -> xy`` proposes a footprint centre for a footprint of radius ``r``;
    ``accept(world_vertices) -> bool`` can veto a placement. A shape that finds no place in 200
    tries is dropped.
    """
    prims, meshes, circles = [], [], []
    for kind, params, mesh, rotation in shapes:
        rotated = mesh.vertices @ rotation.T
        r = float(np.linalg.norm(rotated[:, :2], axis=1).max())
        lift = -float(rotated[:, 2].min())
        if rng.uniform() < float_prob:
            lift += rng.uniform(0.0, 0.6) * r
        for tries in range(200):
            xy = sample(r, tries)
            if any(np.linalg.norm(xy - c) < r + rc for c, rc in circles):
                continue
            pose = np.eye(4)
            pose[:3, :3] = rotation
            pose[:3, 3] = [xy[0], xy[1], lift]
            if not accept(_world_pose(pose, mesh.vertices)):
                continue
            size = float(np.linalg.norm(mesh.extents)) / 2
            prims.append(Primitive(kind, params, pose, random_texture(rng), round(size * rng.uniform(0.8, 2.0), 4),
                                   len(prims) + 1))
            meshes.append(mesh)
            circles.append((xy, r))
            break
    return prims, meshes


def _world_pose(pose: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Local vertices ``# [P, 3]`` to world."""
    return local @ pose[:3, :3].T + pose[:3, 3]


def _unit2(rng) -> np.ndarray:
    a = rng.uniform(0, 2 * np.pi)
    return np.array([math.cos(a), math.sin(a)])


def _light(rng, forward: bool) -> Lighting:
    elevation = math.radians(rng.uniform(35, 75))
    # forward scenes: light from behind the cameras (they look along +y), so fronts are lit
    azimuth = math.radians(rng.uniform(-150, -30)) if forward else rng.uniform(0, 2 * np.pi)
    direction = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                          math.sin(elevation)])
    return Lighting(direction, ambient=round(float(rng.uniform(0.3, 0.5)), 4),
                    intensity=round(float(rng.uniform(1.0, 1.25)), 4))


def _background(rng) -> list[float]:
    choice = rng.integers(3)
    if choice == 0:
        return [1.0, 1.0, 1.0]
    if choice == 1:
        return [0.0, 0.0, 0.0]
    return random_color(rng, (0.3, 0.9))


def _add_ground(layout: Layout, rng, quads: list[np.ndarray], tile: float, cells: int = 8) -> None:
    """Planar ground quads (corners counter-clockwise seen from the front), each split into a
    ``cells x cells`` grid of triangle pairs: the same plane, but small triangles rasterize with
    less waste than two huge ones."""
    t = np.linspace(0.0, 1.0, cells + 1)
    s, r = np.meshgrid(t, t, indexing="xy")  # [cells+1, cells+1]: s along edge 0-1, r along edge 0-3
    i = np.arange(cells)
    a = (i[:, None] * (cells + 1) + i[None, :]).ravel()  # lower-left corner index of each cell
    up = a + cells + 1  # the corner above
    cell_faces = np.concatenate([np.stack([a, a + 1, up + 1], 1), np.stack([a, up + 1, up], 1)])
    vertices, faces = [], []
    for q, c in enumerate(quads):
        grid = (c[0] + s[..., None] * (c[1] - c[0]) + r[..., None] * (c[3] - c[0])).reshape(-1, 3)
        vertices.append(grid)
        faces.append(cell_faces + q * len(grid))
    layout.ground_vertices = np.concatenate(vertices)
    layout.ground_faces = np.concatenate(faces)
    layout.ground_texture = random_texture(rng)
    layout.ground_tile = round(float(tile), 4)
