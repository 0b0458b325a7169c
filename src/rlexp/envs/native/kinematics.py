"""Batched forward kinematics of a serial chain, in numpy, for all envs at once.

MuJoCo computes body poses one ``mjData`` at a time; the physics of all envs advances in C
(``mujoco.rollout``) and only the raw state comes back, so the end-effector pose is recomputed here
from joint positions with the model's own body offsets, exactly as ``mj_kinematics`` does.
"""

from __future__ import annotations

import mujoco
import numpy as np

# R = Q @ C: the rotation matrix (row-major, 9) of a quaternion (w, x, y, z) as a quadratic form of
# the 16 products q_k q_l (homogeneous, so it holds for any unit quaternion); one matmul for all N.
_QUAT_TO_MAT = np.zeros((16, 9))
for _ij, _terms in enumerate(
    [
        [(0, 0, 1), (1, 1, 1), (2, 2, -1), (3, 3, -1)],
        [(1, 2, 2), (0, 3, -2)],
        [(1, 3, 2), (0, 2, 2)],
        [(1, 2, 2), (0, 3, 2)],
        [(0, 0, 1), (1, 1, -1), (2, 2, 1), (3, 3, -1)],
        [(2, 3, 2), (0, 1, -2)],
        [(1, 3, 2), (0, 2, -2)],
        [(2, 3, 2), (0, 1, 2)],
        [(0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, 1)],
    ]
):
    for _k, _l, _c in _terms:
        _QUAT_TO_MAT[4 * _k + _l, _ij] += _c


def quat_to_mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] from unit quaternions [..., 4] (w, x, y, z)."""
    qq = (quat[..., :, None] * quat[..., None, :]).reshape(quat.shape[:-1] + (16,))
    return (qq @ _QUAT_TO_MAT).reshape(quat.shape[:-1] + (3, 3))


def mat_to_quat(mat: np.ndarray) -> np.ndarray:
    """Unit quaternions [..., 4] (w, x, y, z, w >= 0) from rotation matrices [..., 3, 3]."""
    m = mat
    t = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # four candidate formulas; take the numerically largest denominator per row
    cands = np.stack(
        [
            np.stack(
                [
                    1 + t,
                    m[..., 2, 1] - m[..., 1, 2],
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
                ],
                -1,
            ),
        ],
        -2,
    )
    diag = np.stack(
        [
            1 + t,
            1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
        ],
        -1,
    )
    best = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


class SerialChainFK:
    """Pose of a site at the end of a chain of bodies with one hinge or slide joint each (or none).

    Each link is a homogeneous transform [[B R(q), p + d q], [0, 1]] in its parent's frame: B, p the
    body's fixed rotation and offset, R(q) = I + sin q K + (1 - cos q) K^2 (Rodrigues) for a hinge,
    d = B axis for a slide. All links of all envs are built at once from constant matrices, then
    composed with one batched 4x4 product per link.
    """

    def __init__(self, model: mujoco.MjModel, site: str) -> None:
        site_id = model.site(site).id
        body = int(model.site_bodyid[site_id])
        chain = []
        while body != 0:
            chain.append(body)
            body = int(model.body_parentid[body])
        chain.reverse()
        nl = len(chain)
        self._a = np.zeros(
            (3, nl, 4, 4)
        )  # constant, sin q and (1 - cos q) parts of each link transform
        self._a[0, :, 3, 3] = 1.0
        self._slide = np.zeros((nl, 4, 4))  # translation per unit of slide joint position
        adrs = np.zeros(nl, dtype=int)
        self._is_hinge = np.zeros(nl, dtype=bool)
        self._is_slide = np.zeros(nl, dtype=bool)
        for i, b in enumerate(chain):
            njnt = int(model.body_jntnum[b])
            if njnt > 1:
                raise ValueError(
                    f"body {model.body(b).name!r} has {njnt} joints; the FK chain takes one per body"
                )
            brot = quat_to_mat(model.body_quat[b].copy())
            self._a[0, i, :3, :3] = brot
            self._a[0, i, :3, 3] = model.body_pos[b]
            if njnt == 1:
                j = int(model.body_jntadr[b])
                kind, axis, adrs[i] = (
                    int(model.jnt_type[j]),
                    model.jnt_axis[j],
                    int(model.jnt_qposadr[j]),
                )
                if kind == mujoco.mjtJoint.mjJNT_HINGE:
                    if model.jnt_pos[j].any():
                        raise ValueError(
                            f"joint {model.joint(j).name!r}: hinge anchors off the body origin are not supported"
                        )
                    k = np.array(
                        [[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]
                    )
                    self._a[1, i, :3, :3] = brot @ k
                    self._a[2, i, :3, :3] = brot @ k @ k
                    self._is_hinge[i] = True
                elif kind == mujoco.mjtJoint.mjJNT_SLIDE:
                    self._slide[i, :3, 3] = brot @ axis
                    self._is_slide[i] = True
                else:
                    raise ValueError(f"joint {model.joint(j).name!r} is not a hinge or slide joint")
        # Fold the jointless bodies (fixed transforms) and the site into their neighbouring joint links,
        # so only one transform per joint remains to be composed.
        moving = self._is_hinge | self._is_slide
        if not moving.any():
            raise ValueError(f"site {site!r}: no joint on its chain")
        site_t = np.eye(4)
        site_t[:3, :3] = quat_to_mat(model.site_quat[site_id].copy())
        site_t[:3, 3] = model.site_pos[site_id]
        idx = np.flatnonzero(moving)
        basis = self._a[:, idx].copy()  # [3, J, 4, 4]
        slide = self._slide[idx].copy()
        prefix = np.eye(4)
        for i in range(idx[0]):  # fixed bodies before the first joint
            prefix = prefix @ self._a[0, i]
        basis[:, 0] = prefix @ basis[:, 0]
        slide[0] = prefix @ slide[0]
        for k, i in enumerate(
            idx
        ):  # fixed bodies after joint k, up to the next joint (or the site)
            end = idx[k + 1] if k + 1 < len(idx) else len(chain)
            suffix = np.eye(4)
            for f in range(i + 1, end):
                suffix = suffix @ self._a[0, f]
            if k + 1 == len(idx):
                suffix = suffix @ site_t
            basis[:, k] = basis[:, k] @ suffix
            slide[k] = slide[k] @ suffix
        self._hinge_mask = self._is_hinge[idx]
        self._slide_mask = self._is_slide[idx]
        self._any_slide = bool(self._slide_mask.any())
        parts = [basis[0], basis[1], basis[2]] + ([slide] if self._any_slide else [])
        self._basis = np.stack(parts, axis=1).reshape(len(idx), len(parts), 16)  # [J, K, 16]
        self.qpos_adr = adrs[idx]

    def __call__(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Site position [N, 3] and rotation [N, 3, 3] (world frame) for joint positions qpos [N, nq]."""
        q = qpos[:, self.qpos_adr].T  # [J, N]
        nj, n = q.shape
        coef = np.empty((nj, n, self._basis.shape[1]))
        coef[:, :, 0] = 1.0
        qh = np.where(self._hinge_mask[:, None], q, 0.0)
        np.sin(qh, out=coef[:, :, 1])
        np.cos(qh, out=coef[:, :, 2])
        np.subtract(1.0, coef[:, :, 2], out=coef[:, :, 2])
        if self._any_slide:
            coef[:, :, 3] = np.where(self._slide_mask[:, None], q, 0.0)
        t = (coef @ self._basis).reshape(nj, n, 4, 4)  # every joint's link transform, all envs
        # compose pairwise: a few larger batched products instead of many small ones
        while t.shape[0] > 1:
            paired = t[0 : t.shape[0] - 1 : 2] @ t[1::2]
            t = np.concatenate([paired, t[-1:]]) if t.shape[0] % 2 else paired
        t = t[0]
        return t[:, :3, 3], t[:, :3, :3]
