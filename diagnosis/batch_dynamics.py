"""Window-vectorised rigid-body terms of the nominal arm for model diagnosis: recursive Newton-Euler (Eq. 1,
tau = M ddq + C dq + G) over T samples at once on Robot.body_frames' kinematics, the gravity map G(q; g), and the
end-effector payload regressors (Eqs. 4-5 and the 10-parameter rigid body). Checked against dynamics.Robot (MuJoCo)."""
from __future__ import annotations

import mujoco
import numpy as np

from dynamics import Robot, skew


def _cross(a, b):
    """a x b for (T, 3) arrays (or one of them (3,)); faster than np.cross on long windows."""
    a, b = np.broadcast_arrays(a, b)
    out = np.empty(a.shape)
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def _mv(R, v):
    """R v for R (T, 3, 3) and v (T, 3) or (3,) -> (T, 3)."""
    if v.ndim == 1:
        return (R.reshape(-1, 3) @ v).reshape(R.shape[0], 3)
    return (R * v[:, None, :]).sum(axis=2)


def _mm(A, B):
    """A B for A (T, 3, 3) and B (3, 3) or (T, 3, 3) -> (T, 3, 3)."""
    if B.ndim == 2:
        return (A.reshape(-1, 3) @ B).reshape(A.shape)
    return np.einsum("tij,tjk->tik", A, B)


def _quat2mat(quat):
    R = np.empty(9)
    mujoco.mju_quat2Mat(R, np.asarray(quat, dtype=float))
    return R.reshape(3, 3)


def _inertia_times(v):
    """L(v) (T, 3, 6) with I v = L(v) (Ixx, Ixy, Iyy, Ixz, Iyz, Izz) for v (T, 3)."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    L = np.zeros(v.shape[:1] + (3, 6))
    L[:, 0, 0], L[:, 0, 1], L[:, 0, 3] = x, y, z
    L[:, 1, 1], L[:, 1, 2], L[:, 1, 4] = x, y, z
    L[:, 2, 3], L[:, 2, 4], L[:, 2, 5] = x, y, z
    return L


class BatchDynamics:
    """The robot's bodies (a tree, one hinge or none per body) read from its MjModel, evaluated on windows.

    forward(q, dq, ddq, g) runs the world-frame Newton-Euler recursion (e.g. Featherstone, Rigid Body Dynamics
    Algorithms, Ch. 5) with the base accelerating at -g; the result holds per-body poses, joint axes z and anchors o,
    and per-joint subtree first moments s_j = sum_b m_b (c_b - o_j), so G(q; v) = -(z_j x s_j) . v for any gravity v.
    """

    def __init__(self, robot: Robot):
        m = robot.model
        self.robot, self.n, self.nbody = robot, robot.n, m.nbody
        self.parent = m.body_parentid.copy()
        self.dof = np.full(m.nbody, -1)
        for j in range(m.njnt):
            self.dof[m.jnt_bodyid[j]] = m.jnt_dofadr[j]
        self.mass, self.ipos = m.body_mass.copy(), m.body_ipos.copy()
        self.inertia = [_quat2mat(m.body_iquat[b]) @ np.diag(m.body_inertia[b]) @ _quat2mat(m.body_iquat[b]).T
                        for b in range(m.nbody)]
        self.armature = m.dof_armature.copy()
        self.site_body, self.site_pos = int(m.site_bodyid[robot.site]), m.site_pos[robot.site].copy()
        self.site_R0 = _quat2mat(m.site_quat[robot.site])
        chain, b = [], self.site_body
        while b > 0:
            chain.append(b)
            b = self.parent[b]
        self.ee_dofs = np.array(sorted(self.dof[c] for c in chain if self.dof[c] >= 0), dtype=int)
        if len(set(m.jnt_bodyid)) != m.njnt:
            raise ValueError("robot: expected at most one joint per body, found a body with several")

    def forward(self, q, dq, ddq, g) -> dict:
        """Kinematics and joint torques tau = M ddq + C dq + G(q; g) (T, n) for q, dq, ddq (T, n), gravity g (3,).
        Body poses, joint axes and anchors come from the robot's window forward kinematics (Robot.body_frames);
        velocities and accelerations are propagated here."""
        T, nb = q.shape[0], self.nbody
        f = self.robot.body_frames(q)
        p, R, z, o = f["p"], f["R"], f["z"], f["o"]
        zero3 = np.zeros((T, 3))
        w, al, a = [zero3] * nb, [zero3] * nb, [np.broadcast_to(-np.asarray(g, float), (T, 3))] * nb
        c = [zero3] * nb
        for b in range(1, nb):
            pa, j = self.parent[b], self.dof[b]
            if j >= 0:
                zj, anchor, qd = z[:, j], o[:, j], dq[:, j:j + 1]
                w[b] = w[pa] + zj * qd
                al[b] = al[pa] + zj * ddq[:, j:j + 1] + _cross(w[pa], zj * qd)
                a[b] = (a[pa] + _transport(al[pa], w[pa], anchor - p[pa])) + _transport(al[b], w[b], p[b] - anchor)
            else:                                                        # welded: a point fixed on the parent
                w[b], al[b], a[b] = w[pa], al[pa], a[pa] + _transport(al[pa], w[pa], p[b] - p[pa])
            c[b] = p[b] + _mv(R[b], self.ipos[b])
        return self._backward(dict(p=p, R=R, w=w, al=al, a=a, c=c, z=z, o=o), ddq)

    def _backward(self, k, ddq):
        """Sum forces up the tree: F_b (T, 3), N_b about p_b; tau_j = z_j . (N_b + (p_b - o_j) x F_b)."""
        T, nb = ddq.shape[0], self.nbody
        F, N = [np.zeros((T, 3)) for _ in range(nb)], [np.zeros((T, 3)) for _ in range(nb)]
        mass_sub, moment_sub = np.zeros((nb, T)), [np.zeros((T, 3)) for _ in range(nb)]
        tau, s = np.zeros((T, self.n)), np.zeros((T, self.n, 3))
        for b in range(nb - 1, 0, -1):
            p, R, w, al = k["p"][b], k["R"][b], k["w"][b], k["al"][b]
            rc = k["c"][b] - p
            f = self.mass[b] * (k["a"][b] + _transport(al, w, rc))
            Rt = R.transpose(0, 2, 1)
            Iw_w = _mv(R, _mv(Rt, w) @ self.inertia[b])          # world inertia R I R^T times w
            Iw_al = _mv(R, _mv(Rt, al) @ self.inertia[b])
            F[b] += f
            N[b] += Iw_al + _cross(w, Iw_w) + _cross(rc, f)
            mass_sub[b] += self.mass[b]
            moment_sub[b] += self.mass[b] * k["c"][b]
            j = self.dof[b]
            if j >= 0:
                o = k["o"][:, j]
                tau[:, j] = (k["z"][:, j] * (N[b] + _cross(p - o, F[b]))).sum(axis=1)
                tau[:, j] += self.armature[j] * ddq[:, j]
                s[:, j] = moment_sub[b] - mass_sub[b][:, None] * o
            pa = self.parent[b]
            F[pa] += F[b]
            N[pa] += N[b] + _cross(p - k["p"][pa], F[b])
            mass_sub[pa] += mass_sub[b]
            moment_sub[pa] += moment_sub[b]
        k.update(tau=tau, W=np.cross(k["z"], s))
        return k

    # --- end-effector terms ---------------------------------------------------------------------
    def site(self, k):
        """The ee site: p (T, 3), R (T, 3, 3), w, al, a (classical, including -g) (T, 3) in world, Jv, Jw (T, n, 3)."""
        b = self.site_body
        r = _mv(k["R"][b], self.site_pos)
        p, R = k["p"][b] + r, _mm(k["R"][b], self.site_R0)
        a = k["a"][b] + _transport(k["al"][b], k["w"][b], r)
        Jv, Jw = np.zeros_like(k["z"]), np.zeros_like(k["z"])
        d = self.ee_dofs
        Jw[:, d] = k["z"][:, d]
        Jv[:, d] = np.cross(k["z"][:, d], p[:, None, :] - k["o"][:, d])
        return p, R, k["w"][b], k["al"][b], a, Jv, Jw

    def payload_regressor(self, k, g):
        """Y (T, n, 4), tau_mm = Y phi, phi = (m, m r) with r in the ee frame (paper sign, as Robot.payload_regressor):
        F = m g, N = (R r) x F  =>  column 0: Jv g; column 1 + i: Jw ((R e_i) x g)."""
        _, R, _, _, _, Jv, Jw = self.site(k)
        Y = np.empty(Jv.shape[:2] + (4,))
        Y[:, :, 0] = Jv @ g
        Y[:, :, 1:] = Jw @ np.cross(R.transpose(0, 2, 1), g).transpose(0, 2, 1)
        return Y

    def body_regressor(self, k):
        """Y (T, n, 10), tau = Y pi for a rigid payload pi = (m, m c, Ixx, Ixy, Iyy, Ixz, Iyz, Izz) about the ee origin
        in the ee frame (paper sign, as Robot.body_regressor). Newton-Euler in the ee frame with a = R^T (a_ee - g):
        f = m a + al x h + w x (w x h), n = I al + w x (I w) + h x a; tau = -(Jv^T R f + Jw^T R n)."""
        _, R, w, al, a, Jv, Jw = self.site(k)
        Rt = R.transpose(0, 2, 1)
        w, al, a = (_mv(Rt, v) for v in (w, al, a))
        T = w.shape[0]
        f, n = np.zeros((T, 3, 10)), np.zeros((T, 3, 10))
        f[:, :, 0] = a
        f[:, :, 1:4] = skew(al) + skew(w) @ skew(w)
        n[:, :, 1:4] = -skew(a)
        n[:, :, 4:] = _inertia_times(al) + skew(w) @ _inertia_times(w)
        return -(Jv @ (R @ f) + Jw @ (R @ n))


def _transport(al, w, r):
    """Acceleration difference between two points of one rigid body: al x r + w x (w x r), all (T, 3)."""
    return _cross(al, r) + _cross(w, _cross(w, r))
