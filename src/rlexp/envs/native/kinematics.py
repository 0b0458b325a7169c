"""Batched forward kinematics of a serial chain, in numpy, for all envs at once.

MuJoCo computes body poses one ``mjData`` at a time; the physics of all envs advances in C
(``mujoco.rollout``) and only the raw state comes back, so the end-effector pose is recomputed here
from joint positions with the model's own body offsets, exactly as ``mj_kinematics`` does.
"""

from __future__ import annotations

import mujoco
import numpy as np


def quat_to_mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] from unit quaternions [..., 4] (w, x, y, z)."""
    w, x, y, z = np.moveaxis(quat, -1, 0)
    out = np.empty(quat.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def mat_to_quat(mat: np.ndarray) -> np.ndarray:
    """Unit quaternions [..., 4] (w, x, y, z, w >= 0) from rotation matrices [..., 3, 3]."""
    m = mat
    t = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # four candidate formulas; take the numerically largest denominator per row
    cands = np.stack(
        [
            np.stack([1 + t, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            np.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            np.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
            np.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1),
        ],
        -2,
    )
    diag = np.stack([1 + t, 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1)
    best = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


class SerialChainFK:
    """Pose of a site at the end of a chain of bodies with one hinge or slide joint each (or none)."""

    def __init__(self, model: mujoco.MjModel, site: str) -> None:
        site_id = model.site(site).id
        body = int(model.site_bodyid[site_id])
        chain = []
        while body != 0:
            chain.append(body)
            body = int(model.body_parentid[body])
        chain.reverse()
        # per body: fixed offset (pos, rot) in the parent frame, then its joint (kind, axis, anchor, qpos address)
        self._links: list[tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, int]] = []
        for b in chain:
            njnt = int(model.body_jntnum[b])
            if njnt > 1:
                raise ValueError(f"body {model.body(b).name!r} has {njnt} joints; the FK chain takes one per body")
            kind, axis, anchor, adr = -1, np.zeros(3), np.zeros(3), -1
            if njnt == 1:
                j = int(model.body_jntadr[b])
                kind = int(model.jnt_type[j])
                if kind not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
                    raise ValueError(f"joint {model.joint(j).name!r} is not a hinge or slide joint")
                axis, anchor, adr = model.jnt_axis[j].copy(), model.jnt_pos[j].copy(), int(model.jnt_qposadr[j])
            self._links.append(
                (model.body_pos[b].copy(), quat_to_mat(model.body_quat[b].copy()), kind, axis, anchor, adr)
            )
        self._site_pos = model.site_pos[site_id].copy()
        self._site_rot = quat_to_mat(model.site_quat[site_id].copy())
        self.qpos_adr = np.array([link[5] for link in self._links if link[5] >= 0])

    def __call__(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Site position [N, 3] and rotation [N, 3, 3] (world frame) for joint positions qpos [N, nq]."""
        n = qpos.shape[0]
        pos = np.zeros((n, 3))
        rot = np.broadcast_to(np.eye(3), (n, 3, 3))
        for bpos, brot, kind, axis, anchor, adr in self._links:
            pos = pos + rot @ bpos
            rot = rot @ brot
            if kind == mujoco.mjtJoint.mjJNT_HINGE:
                q = qpos[:, adr]
                # Rodrigues: R(axis, q) = I + sin q K + (1 - cos q) K^2
                k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
                jr = np.eye(3) + np.sin(q)[:, None, None] * k + (1 - np.cos(q))[:, None, None] * (k @ k)
                if anchor.any():  # rotate about the anchor point, not the body origin
                    pos = pos + rot @ anchor - (rot @ jr) @ anchor
                rot = rot @ jr
            elif kind == mujoco.mjtJoint.mjJNT_SLIDE:
                pos = pos + (rot @ axis) * qpos[:, adr, None]
        return pos + rot @ self._site_pos, rot @ self._site_rot
