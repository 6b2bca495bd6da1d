"""Camera trajectories a video segmenter can watch: pseudo-temporal order and smooth paths."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from sagonline.scene.cameras import Camera, make_camera


def pseudo_temporal_order(cameras: list[Camera]) -> list[Camera]:
    """The dataset's views sorted lexicographically by name (the NVOS / SPIn-NeRF protocol)."""
    return sorted(cameras, key=lambda c: c.name)


def viewing_angles(a: list[Camera], b: list[Camera]) -> np.ndarray:
    """(len(a), len(b)) angles in degrees between the cameras' optical axes."""
    u, v = (torch.stack([c.world_to_cam[2, :3] for c in cams]).double().cpu() for cams in (a, b))
    u, v = u / u.norm(dim=1, keepdim=True), v / v.norm(dim=1, keepdim=True)
    cos = u @ v.T
    sin = torch.linalg.cross(u[:, None].expand(-1, len(v), -1), v[None].expand(len(u), -1, -1))
    return np.degrees(torch.atan2(sin.norm(dim=-1), cos).numpy())  # accurate near 0 as well


def nearest_view(cameras: list[Camera], others: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """For each camera, the viewing angle (degrees) to the nearest of `others` and the distance
    between their centres (scene units); nearest by angle. Both (len(cameras),)."""
    angles = viewing_angles(cameras, others)
    nearest = angles.argmin(1)
    ca = torch.stack([c.center for c in cameras]).double().cpu()
    cb = torch.stack([c.center for c in others]).double().cpu()
    dist = (ca - cb[torch.from_numpy(nearest)]).norm(dim=1).numpy()
    return angles[np.arange(len(cameras)), nearest], dist


def shortest_path_order(cameras: list[Camera], start: int = 0) -> list[int]:
    """An order of the views that moves the camera as little as possible between frames: the
    nearest unvisited view next (by viewing angle plus centre distance over the capture's
    radius, in degrees), from `start`, then 2-opt moves while one shortens the path. For
    captures with no protocol order; indices into `cameras`."""
    n = len(cameras)
    if n < 3:
        return list(range(n))
    centres = torch.stack([c.center for c in cameras]).double().cpu()
    radius = float((centres - centres.mean(0)).norm(dim=1).max()) or 1.0
    cost = viewing_angles(cameras, cameras) + np.degrees(
        (torch.cdist(centres, centres) / radius).numpy()
    )
    order, left = [start], set(range(n)) - {start}
    while left:
        here = order[-1]
        nxt = min(left, key=lambda j: (cost[here, j], j))
        order.append(nxt)
        left.remove(nxt)
    improved = True
    while improved:  # 2-opt on an open path: reverse order[i:j+1] when it shortens the path
        improved = False
        for i in range(1, n - 1):
            for j in range(i + 1, n):
                a, b = order[i - 1], order[i]
                c = order[j]
                d = order[j + 1] if j + 1 < n else None
                before = cost[a, b] + (cost[c, d] if d is not None else 0.0)
                after = cost[a, c] + (cost[b, d] if d is not None else 0.0)
                if after < before - 1e-9:
                    order[i : j + 1] = order[i : j + 1][::-1]
                    improved = True
    return order


def path_steps(cameras: list[Camera]) -> np.ndarray:
    """(T-1,) viewing-angle change in degrees between consecutive cameras."""
    if len(cameras) < 2:
        return np.zeros(0)
    return np.diag(viewing_angles(cameras[:-1], cameras[1:]))


def smooth_path(keyframes: list[Camera], num_frames: int, *, loop: bool = False) -> list[Camera]:
    """`num_frames` cameras along the keyframes: slerped rotations, interpolated centres and
    intrinsics, evenly spaced in keyframe parameter. All keyframes must share one image size
    (rescale with `Camera.scaled` first). With `loop`, the path returns to the first keyframe.
    """
    if len(keyframes) < 1 or num_frames < 1:
        raise ValueError("smooth_path needs at least one keyframe and one frame")
    sizes = {(c.width, c.height) for c in keyframes}
    if len(sizes) > 1:
        raise ValueError(
            f"keyframes have different image sizes {sorted(sizes)}; rescale them first"
        )
    keys = list(keyframes) + ([keyframes[0]] if loop else [])
    if len(keys) == 1:
        return [keys[0]] * num_frames
    w2c = np.stack([c.world_to_cam.double().numpy() for c in keys])
    c2w_rot = np.transpose(w2c[:, :3, :3], (0, 2, 1))
    centers = np.stack([c.center.double().numpy() for c in keys])
    Ks = np.stack([c.K.double().numpy() for c in keys])
    knots = np.arange(len(keys), dtype=np.float64)
    slerp = Slerp(knots, Rotation.from_matrix(c2w_rot))
    end = len(keys) - 1
    ts = np.linspace(0.0, end, num_frames, endpoint=not loop)
    rots = slerp(ts).as_matrix()
    width, height = keys[0].width, keys[0].height
    path = []
    for i, t in enumerate(ts):
        j = min(int(np.floor(t)), end - 1)
        a = t - j
        center = (1 - a) * centers[j] + a * centers[j + 1]
        K = (1 - a) * Ks[j] + a * Ks[j + 1]
        m = np.eye(4)
        m[:3, :3] = rots[i].T
        m[:3, 3] = -rots[i].T @ center
        path.append(make_camera(K, m, width, height, f"path_{i:05d}"))
    return path


def insert_between(cameras: list[Camera], count: int) -> list[Camera]:
    """The cameras in their order with `count` cameras slerped in between each consecutive
    pair (named '<previous>+<i>'), so a video segmenter sees small steps; the given cameras
    stay as they are."""
    if count <= 0 or len(cameras) < 2:
        return list(cameras)
    out = []
    for a, b in zip(cameras, cameras[1:], strict=False):
        out.append(a)
        between = smooth_path([a, b], count + 2)[1:-1]
        out += [replace(c, name=f"{a.name}+{i + 1}") for i, c in enumerate(between)]
    out.append(cameras[-1])
    return out


def orbit(
    center,
    radius: float,
    height: float,
    num_frames: int,
    K: np.ndarray,
    width: int,
    height_px: int,
    *,
    up=(0.0, 0.0, 1.0),
    start_deg: float = 0.0,
    span_deg: float = 360.0,
    prefix: str = "orbit",
) -> list[Camera]:
    """Cameras on a circle around `center` at `height` above it, all looking at `center`."""
    from sagonline.scene.cameras import look_at

    center = np.asarray(center, dtype=np.float64)
    full = abs(span_deg - 360.0) < 1e-9
    angles = np.deg2rad(start_deg + np.linspace(0.0, span_deg, num_frames, endpoint=not full))
    cams = []
    for i, a in enumerate(angles):
        eye = center + np.array([radius * np.cos(a), radius * np.sin(a), height])
        cams.append(make_camera(K, look_at(eye, center, up), width, height_px, f"{prefix}_{i:05d}"))
    return cams


def ring_around(camera: Camera, center, count: int, prefix: str = "orbit") -> list[Camera]:
    """`count` copies of `camera` turned about the vertical axis through `center`, evenly over
    360 degrees (the first is `camera` itself): a ring of views at the camera's own elevation
    for a scene that comes with one camera. Vertical: the world axis (+-x, +-y, +-z) nearest to
    the camera's up direction (captures are stored z-up or y-up)."""
    from scipy.spatial.transform import Rotation

    w2c = camera.world_to_cam.detach().double().cpu().numpy()
    camera_up = -w2c[1, :3]  # the camera's -y axis in world coordinates
    axis = int(np.argmax(np.abs(camera_up)))
    up = np.eye(3)[axis] * np.sign(camera_up[axis])
    c = np.asarray(center, dtype=np.float64)
    cams = []
    for i in range(count):
        turn = np.eye(4)
        turn[:3, :3] = Rotation.from_rotvec(
            up / np.linalg.norm(up) * 2 * np.pi * i / count
        ).as_matrix()
        turn[:3, 3] = c - turn[:3, :3] @ c  # x -> R (x - c) + c
        new = w2c @ np.linalg.inv(turn)
        cams.append(make_camera(camera.K, new, camera.width, camera.height, f"{prefix}_{i:03d}"))
    return cams


def orbit_around(
    means: torch.Tensor,  # [N, 3] the Gaussians' centres
    count: int,
    width: int = 640,
    height: int = 480,
    fov_deg: float = 60.0,
    inside: bool = False,
) -> tuple[list[Camera], str]:
    """`count` views on a ring around a scene that comes without cameras: centred on the
    median of the Gaussians' centres (N, 3), far enough that 90% of them fit in a
    `fov_deg` view, 25 degrees above the ring's plane; up is the world axis along which the
    scene is thinnest (most scenes are wider than they are tall). `inside`: a scene seen from
    within (a room): the views stand at the centre and turn, looking out at the ring's
    directions, level. Returns the cameras and a line that says what was chosen."""
    pts = means.detach().double().cpu()
    centre = pts.median(dim=0).values
    spread = (pts.quantile(0.95, dim=0) - pts.quantile(0.05, dim=0)).numpy()
    axis = int(np.argmin(spread))
    up = np.eye(3)[axis]
    reach = float((pts - centre).norm(dim=1).quantile(0.9))
    reach = reach if reach > 0 else 1.0
    distance = 1.15 * reach / np.sin(np.deg2rad(fov_deg) / 2)
    focal = 0.5 * width / np.tan(np.deg2rad(fov_deg) / 2)
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    elevation = 0.0 if inside else np.deg2rad(25.0)
    radius, lift = distance * np.cos(elevation), distance * np.sin(elevation)
    a, b = (i for i in range(3) if i != axis)
    c = centre.numpy()
    from sagonline.scene.cameras import look_at

    start = deepest_direction(pts.numpy(), c, a, b, count, fov_deg) if inside else 0
    cams = []
    for i in range(count):
        t = 2 * np.pi * ((i + start) % count) / count
        ring = c.copy()
        ring[a] += radius * np.cos(t)
        ring[b] += radius * np.sin(t)
        ring[axis] += lift
        eye, target = (c, ring) if inside else (ring, c)
        cams.append(make_camera(K, look_at(eye, target, up), width, height, f"orbit_{i:03d}"))
    names = "xyz"
    where = (
        "from the scene's centre looking out (--inside; view 0 faces the deepest part of the scene)"
        if inside
        else f"around the scene (distance {distance:.3g}; a scene seen from within, a room: "
        "--inside)"
    )
    line = (
        f"an orbit of {count} views {where} ({width}x{height}, {fov_deg:g} degree field of "
        f"view, centre {', '.join(f'{v:.3g}' for v in c)}, up +{names[axis]})"
    )
    return cams, line


def deepest_direction(
    pts: np.ndarray, centre: np.ndarray, a: int, b: int, count: int, fov_deg: float
) -> int:
    """Of `count` directions around `centre` in the plane of axes a, b, the one whose view sees
    the most of the scene: the largest median distance of the Gaussians (N, 3) inside its
    horizontal field of view (a near blank wall has a small one)."""
    offset = pts - centre
    theta = np.arctan2(offset[:, b], offset[:, a])
    dist = np.hypot(offset[:, a], offset[:, b])
    half = np.deg2rad(fov_deg) / 2
    best, best_depth = 0, -1.0
    for i in range(count):
        t = 2 * np.pi * i / count
        inside = np.abs(np.angle(np.exp(1j * (theta - t)))) < half
        if inside.sum() < 20:
            continue
        depth = float(np.median(dist[inside]))
        if depth > best_depth:
            best, best_depth = i, depth
    return best


def cameras_to_tensors(
    cameras: list[Camera],
) -> tuple[torch.Tensor, torch.Tensor]:  # [C, 4, 4] world-to-camera, [C, 3, 3] K
    """(C, 4, 4) world-to-camera and (C, 3, 3) intrinsics stacked."""
    return (torch.stack([c.world_to_cam for c in cameras]), torch.stack([c.K for c in cameras]))
