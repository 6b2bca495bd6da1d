"""Deterministic synthetic 2DGS scenes with per-Gaussian instance and semantic ground truth.

A scene is built from surfel-sampled surfaces: textured objects (spheres, boxes, cylinders,
cones, tori) standing on a checkered ground plane, in front of a backdrop (a wall for
forward-facing captures, a surrounding cylinder for 360-degree ones). Every surfel carries the
instance id of the object it belongs to (0 for ground and backdrop) and a semantic class (its
shape). Cameras come on a forward-facing arc (NVOS-like) or a 360-degree orbit
(DesktopObjects-like); ground-truth masks are rendered from the labels. Everything is a pure
function of the settings and the seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from sagonline.scene.cameras import Camera, intrinsics, look_at, make_camera
from sagonline.scene.gaussians import SH_C0, Gaussians, rotmat_to_quat

SHAPES = ("sphere", "box", "cylinder", "cone", "torus")
SEMANTIC_NAMES = ("background",) + SHAPES


@dataclass
class ObjectSpec:
    shape: str
    center: np.ndarray  # (3,) base centre on the ground (z = 0)
    size: float
    color: np.ndarray  # (3,) in [0, 1]
    pattern: str  # "stripes", "checker", "noise", "plain"


@dataclass
class SyntheticScene:
    """Gaussians (N surfels) with labels, cameras, and the objects they came from."""

    gaussians: Gaussians
    instance: torch.Tensor  # (N,) long, 0 = ground/backdrop, 1..K objects
    semantic: torch.Tensor  # (N,) long, index into SEMANTIC_NAMES
    objects: list[ObjectSpec]
    train_cameras: list[Camera]
    eval_cameras: list[Camera]
    layout: str
    meta: dict = field(default_factory=dict)

    @property
    def num_instances(self) -> int:
        """Label count including background 0."""
        return len(self.objects) + 1


# --- surface samplers: each returns points (P, 3), normals (P, 3), uv (P, 2) texture coords ---


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


def _sphere(n: int, r: float):
    d = _fibonacci_sphere(n)
    uv = np.stack([np.arctan2(d[:, 1], d[:, 0]) / np.pi, d[:, 2]], 1)
    return d * r + np.array([0, 0, r]), d, uv


def _box(n: int, half: float, rng):
    # six faces sampled on a jittered grid; the bottom face is skipped (it sits on the ground)
    faces = [(0, 1), (0, -1), (1, 1), (1, -1), (2, 1)]
    per = max(1, n // len(faces))
    k = max(2, int(np.sqrt(per)))
    g = (np.arange(k) + 0.5) / k * 2 - 1
    a, b = np.meshgrid(g, g)
    a, b = a.ravel() * half, b.ravel() * half
    pts, nrm, uv = [], [], []
    for axis, sign in faces:
        p = np.zeros((a.size, 3))
        others = [i for i in range(3) if i != axis]
        p[:, axis] = sign * half
        p[:, others[0]], p[:, others[1]] = a, b
        nn = np.zeros_like(p)
        nn[:, axis] = sign
        pts.append(p)
        nrm.append(nn)
        uv.append(np.stack([a, b], 1) / half)
    pts = np.concatenate(pts) + np.array([0, 0, half])
    return pts, np.concatenate(nrm), np.concatenate(uv)


def _cylinder(n: int, r: float, h: float):
    side_n = int(n * (2 * np.pi * r * h) / (2 * np.pi * r * h + np.pi * r * r))
    k_theta = max(8, int(np.sqrt(side_n * 2 * np.pi * r / h)))
    k_z = max(2, side_n // k_theta)
    th, z = np.meshgrid(
        np.linspace(0, 2 * np.pi, k_theta, endpoint=False), (np.arange(k_z) + 0.5) / k_z * h
    )
    th, z = th.ravel(), z.ravel()
    side = np.stack([r * np.cos(th), r * np.sin(th), z], 1)
    side_n_ = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1)
    cap_n = max(8, n - side.shape[0])
    rad = np.sqrt((np.arange(cap_n) + 0.5) / cap_n) * r
    ang = np.arange(cap_n) * np.pi * (3 - 5**0.5)
    cap = np.stack([rad * np.cos(ang), rad * np.sin(ang), np.full(cap_n, h)], 1)
    pts = np.concatenate([side, cap])
    nrm = np.concatenate([side_n_, np.tile([0.0, 0.0, 1.0], (cap_n, 1))])
    uv = np.concatenate([np.stack([th / np.pi, z / h * 2], 1), cap[:, :2] / r])
    return pts, nrm, uv


def _cone(n: int, r: float, h: float):
    slant = np.hypot(r, h)
    i = np.arange(n) + 0.5
    t = np.sqrt(i / n)  # uniform over the lateral surface
    th = i * np.pi * (3 - 5**0.5)
    rad = r * t
    pts = np.stack([rad * np.cos(th), rad * np.sin(th), h * (1 - t)], 1)
    nrm = np.stack([h / slant * np.cos(th), h / slant * np.sin(th), np.full(n, r / slant)], 1)
    return pts, nrm, np.stack([np.mod(th, 2 * np.pi) / np.pi, t * 2], 1)


def _torus(n: int, big: float, small: float):
    k_u = max(8, int(np.sqrt(n * big / small)))
    k_v = max(6, n // k_u)
    u, v = np.meshgrid(
        np.linspace(0, 2 * np.pi, k_u, endpoint=False),
        np.linspace(0, 2 * np.pi, k_v, endpoint=False),
    )
    u, v = u.ravel(), v.ravel()
    pts = np.stack(
        [
            (big + small * np.cos(v)) * np.cos(u),
            (big + small * np.cos(v)) * np.sin(u),
            small * np.sin(v) + small,
        ],
        1,
    )
    nrm = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], 1)
    return pts, nrm, np.stack([u / np.pi, v / np.pi], 1)


def _shape_area(spec: ObjectSpec) -> float:
    s = spec.size
    return {
        "sphere": 4 * np.pi * s * s,
        "box": 5 * (2 * s) ** 2,
        "cylinder": 2 * np.pi * (0.7 * s) * (2 * s) + np.pi * (0.7 * s) ** 2,
        "cone": np.pi * s * np.hypot(s, 2 * s),
        "torus": 4 * np.pi**2 * s * (0.35 * s),
    }[spec.shape]


def _sample_object(spec: ObjectSpec, n: int, rng):
    s = spec.size
    if spec.shape == "sphere":
        pts, nrm, uv = _sphere(n, s)
    elif spec.shape == "box":
        pts, nrm, uv = _box(n, s, rng)
    elif spec.shape == "cylinder":
        pts, nrm, uv = _cylinder(n, 0.7 * s, 2 * s)
    elif spec.shape == "cone":
        pts, nrm, uv = _cone(n, s, 2 * s)
    else:
        pts, nrm, uv = _torus(n, s, 0.35 * s)
    return pts + spec.center, nrm, _texture(spec.color, spec.pattern, uv, rng)


def _texture(color: np.ndarray, pattern: str, uv: np.ndarray, rng) -> np.ndarray:
    base = np.tile(color, (uv.shape[0], 1))
    if pattern == "stripes":
        f = 0.65 + 0.35 * (np.sin(uv[:, 0] * 6 * np.pi) > 0)
    elif pattern == "checker":
        f = 0.65 + 0.35 * ((np.floor(uv[:, 0] * 3) + np.floor(uv[:, 1] * 3)) % 2)
    elif pattern == "noise":
        f = 0.75 + 0.25 * rng.random(uv.shape[0])
    else:
        f = np.ones(uv.shape[0])
    return np.clip(base * f[:, None] + rng.normal(0, 0.02, base.shape), 0, 1)


def _frames_from_normals(normals: np.ndarray) -> np.ndarray:
    """(P, 3) unit normals -> (P, 3, 3) rotations whose third column is the normal."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(helper, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


def _plane_grid(n: int, x_range, y_range, z: float):
    area = (x_range[1] - x_range[0]) * (y_range[1] - y_range[0])
    step = np.sqrt(area / max(n, 1))
    xs = np.arange(x_range[0] + step / 2, x_range[1], step)
    ys = np.arange(y_range[0] + step / 2, y_range[1], step)
    x, y = np.meshgrid(xs, ys)
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], 1)
    return pts, np.tile([0.0, 0.0, 1.0], (pts.shape[0], 1)), step


FOOTPRINT = {"sphere": 1.0, "box": 2**0.5, "cylinder": 0.7, "cone": 1.0, "torus": 1.35}


def _place_objects(count: int, radius: float, min_gap: float, rng, sizes) -> list[np.ndarray]:
    """Centres on the ground whose footprints (`sizes`: circumscribed radii) never overlap;
    the disc grows by 10% whenever 500 tries find no room."""
    centers: list[np.ndarray] = []
    for i in range(count):
        placed = False
        while not placed:
            for _ in range(500):
                c = rng.uniform(-radius, radius, 2)
                if np.hypot(*c) + sizes[i] > radius + 0.3:
                    continue
                if all(
                    np.hypot(*(c - o[:2])) > sizes[i] + sizes[j] + min_gap
                    for j, o in enumerate(centers)
                ):
                    placed = True
                    break
            if not placed:
                radius *= 1.1
        centers.append(np.array([c[0], c[1], 0.0]))
    return centers


def make_scene(
    *,
    layout: str = "360",
    num_objects: int = 5,
    num_gaussians: int = 20000,
    width: int = 320,
    height: int = 240,
    num_train_views: int = 36,
    num_eval_views: int = 8,
    seed: int = 0,
    focal_scale: float = 1.1,
) -> SyntheticScene:
    """Build a scene.

    layout "forward": one object (instance 1) and distractor-free surroundings, cameras on a
    60-degree arc in front (NVOS-like); layout "360": `num_objects` objects clustered so they
    occlude one another, cameras on a full orbit (DesktopObjects-like). Eval cameras sit between
    the training views (held out: never rendered for the segmenter).

    Why one function: every step draws from one random stream in a fixed order; split into
    pieces, a reordering would silently change every generated scene and its numbers.
    """
    if layout not in ("forward", "360"):
        raise ValueError(f"layout {layout!r} is not 'forward' or '360'")
    rng = np.random.default_rng(seed)
    if layout == "forward":
        num_objects = 1
    palette = rng.permutation(
        np.array(
            [
                [0.85, 0.2, 0.2],
                [0.2, 0.6, 0.9],
                [0.95, 0.75, 0.1],
                [0.3, 0.8, 0.35],
                [0.7, 0.35, 0.85],
                [0.95, 0.5, 0.15],
                [0.1, 0.75, 0.75],
                [0.9, 0.45, 0.6],
                [0.55, 0.55, 0.2],
            ]
        )
    )
    specs = []
    sizes = rng.uniform(0.28, 0.42, num_objects) if layout == "360" else np.array([0.7])
    shape_order = rng.permutation(len(SHAPES))
    shapes = [SHAPES[shape_order[i % len(SHAPES)]] for i in range(num_objects)]
    footprints = [FOOTPRINT[sh] * sz for sh, sz in zip(shapes, sizes, strict=True)]
    centers = (
        _place_objects(num_objects, 1.0, 0.04, rng, footprints)
        if layout == "360"
        else [np.zeros(3)]
    )
    for i in range(num_objects):
        specs.append(
            ObjectSpec(
                shape=shapes[i],
                center=centers[i],
                size=float(sizes[i]),
                color=palette[i % len(palette)],
                pattern=("stripes", "checker", "noise", "plain")[i % 4],
            )
        )

    # Budget: objects get half the surfels (by area), ground and backdrop share the rest.
    obj_budget = num_gaussians // 2
    areas = np.array([_shape_area(s) for s in specs])
    counts = np.maximum(200, (obj_budget * areas / areas.sum()).astype(int))
    pts, nrm, col, inst, sem, scl = [], [], [], [], [], []
    for i, (spec, n) in enumerate(zip(specs, counts, strict=True)):
        p, nn, c = _sample_object(spec, int(n), rng)
        spacing = np.sqrt(_shape_area(spec) / len(p))
        pts.append(p)
        nrm.append(nn)
        col.append(c)
        inst.append(np.full(len(p), i + 1))
        sem.append(np.full(len(p), SEMANTIC_NAMES.index(spec.shape)))
        scl.append(np.full((len(p), 2), 0.6 * spacing))
    rest = num_gaussians - sum(len(p) for p in pts)
    if rest < 0:  # the objects take about 200 surfels each at least
        too_few = f"its {num_objects} object(s) take {num_gaussians - rest}; the ground needs more"
        raise ValueError(f"num_gaussians={num_gaussians} is too few: {too_few}")
    extent = 4.0 if layout == "360" else 3.0
    ground_n = rest // 2 if layout == "forward" else int(rest * 0.45)
    g_pts, g_nrm, step = _plane_grid(ground_n, (-extent, extent), (-extent, extent), 0.0)
    checker = ((np.floor(g_pts[:, 0] / 0.5) + np.floor(g_pts[:, 1] / 0.5)) % 2)[:, None]
    g_col = np.clip(
        np.where(checker > 0, 0.55, 0.35) * np.array([[0.9, 0.85, 0.75]])
        + rng.normal(0, 0.02, (len(g_pts), 3)),
        0,
        1,
    )
    b_n = num_gaussians - sum(len(p) for p in pts) - len(g_pts)
    if layout == "forward":
        # A wall behind the object (cameras look along +y).
        b_pts, _, b_step = _plane_grid(b_n, (-1.5 * extent, 1.5 * extent), (0.0, 3.0), 0.0)
        b_pts = np.stack([b_pts[:, 0], np.full(len(b_pts), extent * 0.8), b_pts[:, 1]], 1)
        b_nrm = np.tile([0.0, -1.0, 0.0], (len(b_pts), 1))
    else:
        # A surrounding cylinder wall.
        radius, h = extent, 2.5
        k_th = max(16, int(np.sqrt(b_n * 2 * np.pi * radius / h)))
        k_z = max(2, b_n // k_th)
        th, z = np.meshgrid(
            np.linspace(0, 2 * np.pi, k_th, endpoint=False), (np.arange(k_z) + 0.5) / k_z * h
        )
        b_pts = np.stack([radius * np.cos(th.ravel()), radius * np.sin(th.ravel()), z.ravel()], 1)
        b_nrm = -np.stack([np.cos(th.ravel()), np.sin(th.ravel()), np.zeros(th.size)], 1)
        b_step = 2 * np.pi * radius / k_th
    stripes = (
        0.5 + 0.2 * np.sin(b_pts[:, 2] * 5.0) + 0.1 * np.sin(b_pts[:, 0] * 3 + b_pts[:, 1] * 3)
    )
    b_col = np.clip(
        stripes[:, None] * np.array([[0.55, 0.65, 0.8]]) + rng.normal(0, 0.02, (len(b_pts), 3)),
        0,
        1,
    )
    pts += [g_pts, b_pts]
    nrm += [g_nrm, b_nrm]
    col += [g_col, b_col]
    inst += [np.zeros(len(g_pts)), np.zeros(len(b_pts))]
    sem += [np.zeros(len(g_pts)), np.zeros(len(b_pts))]
    scl += [np.full((len(g_pts), 2), 0.6 * step), np.full((len(b_pts), 2), 0.6 * b_step)]

    pts, nrm, col = np.concatenate(pts), np.concatenate(nrm), np.concatenate(col)
    rot = _frames_from_normals(nrm)
    quats = rotmat_to_quat(torch.tensor(rot, dtype=torch.float64)).float()
    gaussians = Gaussians(
        means=torch.tensor(pts, dtype=torch.float32),
        quats=quats,
        scales=torch.tensor(np.concatenate(scl), dtype=torch.float32),
        opacities=torch.full((len(pts),), 0.95),
        sh=torch.tensor(((col - 0.5) / SH_C0)[:, None, :], dtype=torch.float32),
        normals=torch.tensor(nrm, dtype=torch.float32),
    )
    train, evals = _cameras(layout, width, height, num_train_views, num_eval_views, focal_scale)
    return SyntheticScene(
        gaussians=gaussians,
        instance=torch.tensor(np.concatenate(inst), dtype=torch.long),
        semantic=torch.tensor(np.concatenate(sem), dtype=torch.long),
        objects=specs,
        train_cameras=train,
        eval_cameras=evals,
        layout=layout,
        meta={"seed": seed, "num_gaussians": len(pts), "width": width, "height": height},
    )


def _cameras(layout: str, width: int, height: int, n_train: int, n_eval: int, focal_scale: float):
    f = focal_scale * width
    K = intrinsics(f, f, width / 2.0, height / 2.0)
    if layout == "forward":
        target = np.array([0.0, 0.0, 0.6])

        def pose(a):
            return look_at([3.6 * np.sin(a), -3.6 * np.cos(a), 1.6 + 0.3 * np.sin(2 * a)], target)

        span = np.deg2rad(30.0)
        train_a = np.linspace(-span, span, n_train)
        eval_a = np.linspace(-span, span, n_eval + 2)[1:-1] + (span / max(n_train, 1))
    else:
        target = np.array([0.0, 0.0, 0.25])

        def pose(a):
            return look_at([3.0 * np.cos(a), 3.0 * np.sin(a), 1.7 + 0.25 * np.sin(3 * a)], target)

        train_a = np.linspace(0, 2 * np.pi, n_train, endpoint=False)
        eval_a = (np.arange(n_eval) + 0.37) * 2 * np.pi / max(n_eval, 1)
    train = [
        make_camera(K, pose(a), width, height, f"train_{i:04d}") for i, a in enumerate(train_a)
    ]
    evals = [make_camera(K, pose(a), width, height, f"eval_{i:04d}") for i, a in enumerate(eval_a)]
    return train, evals
