"""The scenes the fiducial studies render: the sim camera, a tag on a ray from it, twenty-tag frames
(`lab bench fiducials` and its corner and photograph studies share them)."""

from __future__ import annotations

import math
import time


def _camera():
    import numpy as np

    from lab.core.config import load_rig

    c = load_rig().sim.camera
    K = np.array([[c["fx_px"], 0.0, c["cx_px"]], [0.0, c["fy_px"], c["cy_px"]], [0.0, 0.0, 1.0]])
    return K, np.asarray(c["dist"], dtype=float), int(c["width_px"]), int(c["height_px"]), float(c["pixel_noise"]), float(c["blur_px"])


def tag_pose_on_ray(ray, distance_m: float, angle_rad: float, phi: float, psi: float):
    """camera_T_tag for a tag `distance_m` along the unit `ray`, its face normal tilted `angle_rad` off
    the line of sight towards direction `phi`, turned `psi` about its normal."""
    import numpy as np

    from lab.core.geometry import Pose3, Rot3

    back = -np.asarray(ray, dtype=float)
    helper = np.array([1.0, 0.0, 0.0]) if abs(back[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(back, helper)
    a /= np.linalg.norm(a)
    b = np.cross(back, a)
    z = math.cos(angle_rad) * back + math.sin(angle_rad) * (math.cos(phi) * a + math.sin(phi) * b)
    x0 = np.cross([0.0, 1.0, 0.0], z)
    if np.linalg.norm(x0) < 1e-6:
        x0 = np.cross([1.0, 0.0, 0.0], z)
    x0 /= np.linalg.norm(x0)
    y0 = np.cross(z, x0)
    x = math.cos(psi) * x0 + math.sin(psi) * y0
    y = np.cross(z, x)
    return Pose3(Rot3(np.column_stack([x, y, z])), distance_m * np.asarray(ray, dtype=float))


def random_tag_pose(rng, K, width: int, height: int, distance_m: float, size_m: float,
                    max_angle_rad: float = math.radians(60.0)):
    """camera_T_tag for a tag at `distance_m` from the camera, somewhere in the image (kept a tag's
    width from the border), seen `angle` off its normal with a random turn about the normal."""
    import numpy as np

    margin = 1.2 * K[0, 0] * size_m / distance_m
    u = rng.uniform(margin, width - 1 - margin)
    v = rng.uniform(margin, height - 1 - margin)
    ray = np.linalg.solve(K, [u, v, 1.0])
    ray /= np.linalg.norm(ray)
    angle = math.acos(rng.uniform(math.cos(max_angle_rad), 1.0))  # uniform over the spherical cap
    phi = rng.uniform(0, 2 * math.pi)
    psi = rng.uniform(0, 2 * math.pi)
    return tag_pose_on_ray(ray, distance_m, angle, phi, psi), angle


def twenty_tag_frames(frames: int, seed: int) -> list:
    """The timing scene: 1280x720 frames of 20 tags 1.5-2.5 m away in a 5 x 4 grid, like a BORG face
    seen whole, rendered with the sim's noise: [(BGR image, render seconds)]."""
    import numpy as np

    from lab.core.geometry import Pose3
    from sim_devices.render import render_tags

    K, dist, W, H, noise, blur = _camera()
    size = 0.10
    rng = np.random.default_rng([seed, 2])
    out = []
    for _ in range(frames):
        tags = []
        for i in range(20):
            pose, _ = random_tag_pose(rng, K, W, H, rng.uniform(1.5, 2.5), size, math.radians(40))
            u = 130 + (i % 5) * 255 + rng.uniform(-20, 20)
            v = 110 + (i // 5) * 165 + rng.uniform(-15, 15)
            ray = np.linalg.solve(K, [u, v, 1.0])
            ray /= np.linalg.norm(ray)
            tags.append((i, size, Pose3(pose.rotation(), ray * np.linalg.norm(pose.translation()))))
        t0 = time.perf_counter()
        img = render_tags(K, dist, W, H, tags, blur_sigma_px=blur, noise_sigma=noise, rng=rng)
        out.append((img, time.perf_counter() - t0))
    return out
