"""The arm's nominal rigid-body model on MuJoCo (Sec. 2, Eq. 1) and the payload terms the paper adds to it:
tau_mm = J^T [F_m; r_w x F_m] (Eqs. 4-5) with its regressor in phi = (m, m r), and the 10-parameter
rigid-body payload regressor. Every function takes one state q (n,) or a window q (T, n)."""
from __future__ import annotations

import os

import mujoco
import numpy as np

import checks

PANDA_XML = os.path.join(os.path.dirname(os.path.abspath(__file__)), "panda.xml")
Q_READY = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])   # Franka's ready pose (rad)


def as_states(name, x, n, allow_window=True):
    """Checked float array of shape (n,) or (T, n); returns (array (T, n), batched)."""
    if type(x) is np.ndarray and x.shape == (n,) and x.dtype == np.float64 and np.isfinite(x.sum()):
        return x[None], False                          # fast path for the 1 kHz loop
    if (a := checks.real_array(x)) is None:            # bool, complex, text, objects, ragged: refused, never cast
        raise ValueError(f"{name}: expected a real array of shape ({n},) or (T, {n}), found {checks.kind(x)}")
    batched = allow_window and a.ndim == 2 and a.shape[1] == n and a.shape[0] > 0
    if not batched and a.shape != (n,):
        want = f"({n},) or (T, {n})" if allow_window else f"({n},)"
        raise ValueError(f"{name}: expected shape {want}, found {a.shape}")
    if not np.all(np.isfinite(a)):
        idx = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(f"{name}: expected finite values, found {a[idx]} at index {idx}")
    return np.atleast_2d(np.asarray(a, dtype=float)), batched


def phi_of(theta):
    """phi = (m, m rx, m ry, m rz) (..., 4) for theta = (m, rx, ry, rz) (..., 4): the payload parameters in which
    the gravity torque is linear (Eq. 4)."""
    theta = np.asarray(theta, dtype=float)
    return np.concatenate([theta[..., :1], theta[..., :1] * theta[..., 1:]], axis=-1)


def theta_of(phi):                      # theta = (m, r) (..., 4) for phi = (m, m r) (..., 4); r is NaN where m = 0
    phi = np.asarray(phi, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.concatenate([phi[..., :1], phi[..., 1:] / phi[..., :1]], axis=-1)


def pseudo_wrench(J, tau_ext, lam, check=True):
    """W = (J J^T + lam I)^-1 J tau_ext (Sec. 4.1; paper_notes: the paper's formula lacks the inverse): the wrench
    [F; torque] at the ee that would explain tau_ext. J (6, n) or (T, 6, n), tau_ext (n,) or (T, n) -> (6,) or
    (T, 6), in the frame J's rows are expressed in. lam: the damping (no default: the network and the detector
    use different values, NetConfig.lam and DetectorSettings.lam). check=False skips the input checks (the 1 kHz
    loop, whose inputs are checked once upstream)."""
    if not check:
        return np.linalg.solve(J @ np.swapaxes(J, -1, -2) + lam * np.eye(6), (J @ tau_ext[..., None]))[..., 0]
    J = checks.array("J", J, (None,) * np.ndim(J))                 # real, finite (bool, complex refused)
    tau_ext = checks.array("tau_ext", tau_ext, (None,) * np.ndim(tau_ext))
    if J.ndim not in (2, 3) or J.shape[-2] != 6:
        raise ValueError(f"J: expected shape (6, n) or (T, 6, n), found {J.shape}")
    if tau_ext.shape != J.shape[:-2] + J.shape[-1:]:
        raise ValueError(f"tau_ext: expected shape {J.shape[:-2] + J.shape[-1:]}, found {tau_ext.shape}")
    lam = checks.number("lam", lam, "[0, 1e3]", "(damping)")
    A = J @ np.swapaxes(J, -1, -2) + lam * np.eye(6)                      # (..., 6, 6)
    return np.linalg.solve(A, (J @ tau_ext[..., None]))[..., 0]


def skew(v):
    """[v]x for v (..., 3) -> (..., 3, 3), so skew(v) @ w = v x w."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def inertia_matrix(I6):
    """(Ixx, Ixy, Iyy, Ixz, Iyz, Izz) (pinocchio order) -> symmetric (3, 3)."""
    xx, xy, yy, xz, yz, zz = I6
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


class MomentumObserver:
    """De Luca's momentum observer (De Luca et al. 2006), discrete: r (n,) follows the torque acting on the joints
    beyond the model, dr/dt = K (tau_x - r), from q, dq, tau_J alone: in the paper's sign (tau_x = model - tau_J)
    r = K (M dq - p0 - sum dt (tau_J - n' + r)), p0 = M dq at the first state, n' = n - Mdot dq (Mdot by the step's
    difference). terms(q, dq) -> (M (n, n), n = C dq + G (+ joint damping) (n,)); gain K [1/s]; sign: +1 returns the
    paper's sign, -1 libfranka's (tau_ext_hat_filtered); r0 (n,): r at the first state, in that sign (a robot's
    estimate runs before control starts)."""

    def __init__(self, terms, gain: float, sign: int = 1, r0=None):
        self.terms, self.gain, self.sign = terms, float(gain), sign
        self.r = None if r0 is None else sign * np.array(r0, dtype=float)    # (the paper's sign inside)
        self._p0, self._M, self._integral = None, None, None

    def update(self, q, dq, tau_J, dt: float) -> np.ndarray:
        """r after a state q, dq, tau_J (n,), dt [s] after the previous one (the first sets p0 and returns r0)."""
        M, n = self.terms(q, dq)
        if self._p0 is None:
            self._p0 = M @ dq
            self.r = np.zeros(len(dq)) if self.r is None else self.r
            self._integral = -self.r / self.gain
        else:
            self._integral += dt * (tau_J - (n - (M - self._M) / dt @ dq) + self.r)
            self.r = self.gain * (M @ dq - self._p0 - self._integral)
        self._M = M
        return self.sign * self.r


class Robot:
    """Nominal dynamics M(q) ddq + C(q, dq) dq + G(q) = tau of a serial arm of hinge joints (Eq. 1).

    model: the MjModel (fixed); ee: name of the end-effector site. Single-state calls run MuJoCo's own
    functions on a private MjData; window calls of the kinematic terms (ee_pose, jacobian, payload_*) use a
    vectorised forward-kinematics pass over the body tree (body_frames), checked against MuJoCo in the tests.
    """

    def __init__(self, model: mujoco.MjModel, ee: str = "ee"):
        if not isinstance(ee, str):                     # (MuJoCo's name lookup crashes on None)
            raise ValueError(f"ee: expected the name of a site (text), found {ee!r}")
        site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, ee)
        if site < 0:
            names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(model.nsite)]
            raise ValueError(f"ee: no site named {ee!r} in the model; expected one of {names}")
        if model.nq != model.nv or np.any(model.jnt_type != mujoco.mjtJoint.mjJNT_HINGE):
            raise ValueError("model: expected a serial arm of hinge joints only, found joint types "
                             f"{list(model.jnt_type)} (nq={model.nq}, nv={model.nv})")
        self.model, self.ee, self.site = model, ee, site
        self.n = model.nv
        self.g = model.opt.gravity.copy()              # (3,) world gravity, (0, 0, -9.81) by default
        self._g_skew = skew(self.g)
        self.data = mujoco.MjData(model)
        self._M = np.zeros((self.n, self.n))
        self._tree = self._body_tree()

    @classmethod
    def panda(cls) -> "Robot":
        """The project's Panda (panda.xml beside this file), end-effector site "ee"."""
        return cls.from_xml(PANDA_XML, ee="ee")

    @classmethod
    def from_xml(cls, path, ee: str = "ee") -> "Robot":
        if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
            raise ValueError(f"path: expected an MJCF file, found no file at {path!r}")
        try:
            model = mujoco.MjModel.from_xml_path(str(path))
        except Exception as err:                        # MuJoCo reports parse errors as ValueError/Exception
            raise ValueError(f"path: could not load MJCF {path!r}: {err}") from None
        robot = cls(model, ee)
        robot.xml_path = os.path.abspath(str(path))            # saved with fitted models (Model.save)
        return robot

    def torque_limits(self) -> np.ndarray:
        """|tau| limit per joint (n,) [Nm] from the model's force limits: the joint's actfrcrange, each actuator's
        forcerange x gear, and for a plain motor (torque = gain x gear x ctrl) its ctrlrange x gain x gear; inf
        where nothing limits the joint. A position or velocity servo's ctrlrange is a set point, not a torque."""
        m, lim = self.model, np.full(self.n, np.inf)
        for j in range(m.njnt):
            if m.jnt_actfrclimited[j]:
                lim[m.jnt_dofadr[j]] = np.abs(m.jnt_actfrcrange[j]).max()
        for a in range(m.nu):
            if m.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
                continue
            dof, gear = m.jnt_dofadr[m.actuator_trnid[a, 0]], abs(m.actuator_gear[a, 0])
            if m.actuator_forcelimited[a]:
                lim[dof] = min(lim[dof], np.abs(m.actuator_forcerange[a]).max() * gear)
            motor = (m.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_NONE and m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE
                     and m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED)
            if motor and m.actuator_ctrllimited[a]:
                lim[dof] = min(lim[dof], np.abs(m.actuator_ctrlrange[a]).max() * abs(m.actuator_gainprm[a, 0]) * gear)
        return lim

    # --- single-state MuJoCo calls -------------------------------------------------------------
    def _kin(self, q, dq=None):
        m, d = self.model, self.data
        d.qpos[:] = q
        d.qvel[:] = 0.0 if dq is None else dq
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)

    def _jac(self):
        J = np.empty((6, self.n))
        mujoco.mj_jacSite(self.model, self.data, J[:3], J[3:], self.site)
        return J

    def _bias(self):
        mujoco.mj_comVel(self.model, self.data)
        b = np.empty(self.n)
        mujoco.mj_rne(self.model, self.data, 0, b)
        return b

    def _mass(self):
        mujoco.mj_crb(self.model, self.data)
        mujoco.mj_fullM(self.model, self.data, self._M)
        return self._M.copy()

    def _each(self, fn, *arrays):
        """Apply fn to each row of the checked (T, n) arrays; returns stacked results or the single one."""
        (first, batched), rest = arrays[0], arrays[1:]
        if not batched and not any(b for _, b in rest):
            return fn(*(a[0] for a, _ in arrays))
        T = first.shape[0]
        for a, _ in rest:
            if a.shape[0] != T:
                raise ValueError(f"q, dq, ddq: expected the same number of rows (T), found {T} and {a.shape[0]}")
        out = np.stack([fn(*(a[t] for a, _ in arrays)) for t in range(T)])
        return out if batched else out[0]

    def mass_matrix(self, q):
        """M(q) (n, n), or (T, n, n) for a window (includes any armature in the MJCF)."""
        return self._each(lambda qi: (self._kin(qi), self._mass())[1], as_states("q", q, self.n))

    def bias(self, q, dq):
        """C(q, dq) dq + G(q) (n,) / (T, n)."""
        return self._each(lambda qi, dqi: (self._kin(qi, dqi), self._bias())[1],
                          as_states("q", q, self.n), as_states("dq", dq, self.n))

    def gravity(self, q):
        """G(q) (n,) / (T, n): the joint torque that holds the arm still."""
        return self._each(lambda qi: (self._kin(qi), self._bias())[1], as_states("q", q, self.n))

    def inverse_dynamics(self, q, dq, ddq):
        """tau = M(q) ddq + C(q, dq) dq + G(q) (n,) / (T, n)."""
        arm = self.model.dof_armature

        def one(qi, dqi, ddqi):
            self._kin(qi, dqi)
            mujoco.mj_comVel(self.model, self.data)
            self.data.qacc[:] = ddqi
            tau = np.empty(self.n)
            mujoco.mj_rne(self.model, self.data, 1, tau)
            return tau + arm * ddqi                      # mj_rne leaves armature out; mj_crb puts it in M
        return self._each(one, as_states("q", q, self.n), as_states("dq", dq, self.n),
                          as_states("ddq", ddq, self.n))

    def terms(self, q, dq):
        """(J (6, n), M (n, n), C dq + G (n,)) for one state in one pass: what a 1 kHz control step needs."""
        q, _ = as_states("q", q, self.n, allow_window=False)
        dq, _ = as_states("dq", dq, self.n, allow_window=False)
        self._kin(q[0], dq[0])
        return self._jac(), self._mass(), self._bias()

    def control_terms(self, q, dq):
        """Everything a task-space control step needs for one state, in one kinematics pass:
        (J (6, n), M (n, n), b = C dq + G (n,), G (n,), p (3,), R (3, 3))."""
        J, M, b = self.terms(q, dq)
        d = self.data
        p, R = d.site_xpos[self.site].copy(), d.site_xmat[self.site].reshape(3, 3).copy()
        d.qvel[:] = 0.0
        return J, M, b, self._bias(), p, R

    # --- kinematics ----------------------------------------------------------------------------
    def ee_pose(self, q):
        """End-effector origin p (3,) and orientation R (3, 3) (columns: ee axes in world); (T, 3), (T, 3, 3)."""
        q, batched = as_states("q", q, self.n)
        if batched:
            p, R, _, _ = self._fk(q)
            return p, R
        self._kin(q[0])
        return self.data.site_xpos[self.site].copy(), self.data.site_xmat[self.site].reshape(3, 3).copy()

    def jacobian(self, q):
        """J (6, n): world-frame [v; w] = J dq at the end-effector origin, linear rows first; (T, 6, n)."""
        q, batched = as_states("q", q, self.n)
        if batched:
            return self._fk_jacobian(q)[0]
        self._kin(q[0])
        return self._jac()

    def kinematics(self, q):
        """(p (3,), R (3, 3), J (6, n)) of the end-effector in one pass; (T, 3), (T, 3, 3), (T, 6, n) for a window."""
        q, batched = as_states("q", q, self.n)
        if batched:
            J, R, p = self._fk_jacobian(q)
            return p, R, J
        self._kin(q[0])
        return self.data.site_xpos[self.site].copy(), self.data.site_xmat[self.site].reshape(3, 3).copy(), self._jac()

    def _body_tree(self):
        """Per body b >= 1: (parent, pos (3,), R0 (3, 3) fixed in the parent, joint or -1); None when a body has
        several joints (windows then fall back to per-sample MuJoCo calls)."""
        m, tree = self.model, []
        for b in range(1, m.nbody):
            jnts = np.flatnonzero(m.jnt_bodyid == b)
            if len(jnts) > 1:
                return None
            R0 = np.empty(9)
            mujoco.mju_quat2Mat(R0, m.body_quat[b])
            tree.append((int(m.body_parentid[b]), m.body_pos[b].copy(), R0.reshape(3, 3), int(jnts[0]) if len(jnts) else -1))
        Rs = np.empty(9)
        mujoco.mju_quat2Mat(Rs, m.site_quat[self.site])
        self._site_frame = (int(m.site_bodyid[self.site]), m.site_pos[self.site].copy(), Rs.reshape(3, 3))
        self._ee_dofs = np.zeros(self.n)                   # 1 for the joints between the base and the ee site
        b = self._site_frame[0]
        while b > 0:
            for j in np.flatnonzero(m.jnt_bodyid == b):
                self._ee_dofs[m.jnt_dofadr[j]] = 1.0
            b = int(m.body_parentid[b])
        return tree

    def body_frames(self, q):
        """Window forward kinematics over the whole body tree, q (T, n): body origins p and rotations R in the world
        frame (lists over the bodies of (T, 3) and (T, 3, 3), body 0 the world) and the joint axes z and anchors o
        (T, n, 3) in the world frame. A hinge turns its body by q - qpos0 about its axis, as in MuJoCo."""
        q, _ = as_states("q", q, self.n)
        if self._tree is None:
            raise ValueError("robot: body_frames needs at most one joint per body, found a body with several")
        return self._frames(q)

    def _frames(self, q):
        m, T = self.model, q.shape[0]
        p, R = [np.zeros((T, 3))], [np.broadcast_to(np.eye(3), (T, 3, 3))]
        z, o = np.zeros((T, self.n, 3)), np.zeros((T, self.n, 3))
        for parent, pos, R0, jnt in self._tree:            # bodies in MuJoCo's order: parents come first
            pb, Rb = p[parent] + R[parent] @ pos, R[parent] @ R0
            if jnt >= 0:
                dof, a_loc, c_loc = m.jnt_dofadr[jnt], m.jnt_axis[jnt], m.jnt_pos[jnt]
                angle = q[:, m.jnt_qposadr[jnt]] - m.qpos0[m.jnt_qposadr[jnt]]
                anchor = pb + Rb @ c_loc if c_loc.any() else pb                 # (T, 3), fixed on the parent
                if a_loc[0] == 0.0 and a_loc[1] == 0.0 and a_loc[2] > 0.0:    # about the body z axis (DH arms)
                    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
                    x, y = Rb[:, :, 0], Rb[:, :, 1]                           # R_body = R_pre RotZ(q), by columns
                    Rb = np.stack([c * x + s * y, c * y - s * x, Rb[:, :, 2]], axis=2)
                else:
                    Rb = Rb @ _axis_rotation(a_loc, angle)                    # R_body = R_pre Rot(a, q)
                pb = anchor - Rb @ c_loc if c_loc.any() else anchor
                z[:, dof], o[:, dof] = Rb @ (a_loc / np.linalg.norm(a_loc)), anchor
            p.append(pb)
            R.append(Rb)
        return {"p": p, "R": R, "z": z, "o": o}

    def _fk(self, q):
        """Vectorised forward kinematics for q (T, n): site p (T,3), R (T,3,3), joint axes and anchors (T,n,3)
        (axes zero for joints that do not move the ee)."""
        if self._tree is None:
            out = [self.ee_pose(qi) for qi in q]
            return np.stack([o[0] for o in out]), np.stack([o[1] for o in out]), None, None
        f = self._frames(q)
        b, pos, Rs = self._site_frame
        p, R = f["p"][b], f["R"][b]
        return p + R @ pos, R @ Rs, f["z"] * self._ee_dofs[:, None], f["o"]

    def _fk_jacobian(self, q):
        p, R, axes, anchors = self._fk(q)
        if axes is None:
            return np.stack([self.jacobian(qi) for qi in q]), R, p
        J = np.empty((q.shape[0], 6, self.n))
        J[:, :3] = np.cross(axes, p[:, None, :] - anchors).transpose(0, 2, 1)   # z_i x (p - o_i)
        J[:, 3:] = axes.transpose(0, 2, 1)
        return J, R, p

    # --- payload terms (paper Eqs. 4-5) ---------------------------------------------------------
    def payload_regressor(self, q):
        """Y (n, 4) / (T, n, 4) with tau_mm = Y phi, phi = (m, m rx, m ry, m rz), r in the ee frame.

        tau_mm = Jv^T F + Jw^T ((R r) x F), F = m g  =>  Y = [Jv^T g, -Jw^T [g]x R]  (paper sign:
        the torque the payload's weight applies to the arm, like tau_ext).
        """
        q, batched = as_states("q", q, self.n)
        if not batched:
            self._kin(q[0])
            return self.payload_regressor_from(self._jac(), self.data.site_xmat[self.site].reshape(3, 3))
        J, R, _ = self._fk_jacobian(q)
        return self.payload_regressor_from(J, R)

    def payload_regressor_from(self, J, R):
        """Y (n, 4) from an already computed J (6, n) and R (3, 3) of one state, or (T, n, 4) from J (T, 6, n) and
        R (T, 3, 3) of a window (see payload_regressor)."""
        if J.ndim == 2:
            Y = np.empty((self.n, 4))
            Y[:, 0] = self.g @ J[:3]
            Y[:, 1:] = -J[3:].T @ (self._g_skew @ R)
            return Y
        Y = np.empty((J.shape[0], self.n, 4))
        Y[:, :, 0] = self.g @ J[:, :3]
        Y[:, :, 1:] = -J[:, 3:].transpose(0, 2, 1) @ (self._g_skew @ R)
        return Y

    def link_bodies(self) -> tuple:
        """Names of the bodies that carry a joint, base to tip, except the last: the links whose inertial parameters
        a load on the flange cannot stand for (the last link's gravity regressor is the payload's)."""
        m = self.model
        bodies = [int(m.jnt_bodyid[j]) for j in range(m.njnt)]
        return tuple(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in bodies[:-1])

    def link_gravity_regressor(self, q, bodies):
        """A (n, 4 L) with tau = A dpi the gravity torque of the links named in bodies (L of them), dpi = per link
        (m, m cx, m cy, m cz), c the CoM in the link's body frame; paper sign, as payload_regressor (the same form
        at each link's frame origin: [Jv^T g, -Jw^T [g]x R]). q (n,), the pose (a window's mean)."""
        q, _ = as_states("q", q, self.n, allow_window=False)
        m, d = self.model, self.data
        self._kin(q[0])
        A, J = np.empty((self.n, 4 * len(bodies))), np.empty((6, self.n))
        for i, name in enumerate(bodies):
            b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
            if b < 0:
                raise ValueError(f"bodies: no body named {name!r} in the model")
            mujoco.mj_jacBody(m, d, J[:3], J[3:], b)
            A[:, 4 * i:4 * i + 4] = self.payload_regressor_from(J, d.xmat[b].reshape(3, 3))
        return A

    def link_parameters(self, bodies) -> np.ndarray:
        """pi (4 L,) the model's own (m, m cx, m cy, m cz) of the links named in bodies (link_gravity_regressor)."""
        m = self.model
        ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name) for name in bodies]
        return np.concatenate([[m.body_mass[b], *(m.body_mass[b] * m.body_ipos[b])] for b in ids])

    def payload_torque(self, q, theta):
        """tau_mm (n,) / (T, n) for theta = (m, rx, ry, rz) (kg, m in the ee frame)."""
        theta, _ = as_states("theta", theta, 4, allow_window=False)
        return self.payload_regressor(q) @ phi_of(theta[0])

    def body_regressor(self, q, dq, ddq, gravity: bool = True):
        """Y (n, 10) / (T, n, 10): joint torque that a rigid payload applies to the arm under motion,
        tau = Y pi, pi = (m, m cx, m cy, m cz, Ixx, Ixy, Iyy, Ixz, Iyz, Izz), inertia about the ee origin,
        all in the ee frame (pinocchio's order). Same sign as payload_torque: Y(q, 0, 0)[:, :4] == payload_regressor(q).
        gravity False: the motion's part alone, Y(q, dq, ddq) - Y(q, 0, 0) (its weight left out), in the same pass.

        Newton-Euler in the ee frame, a = (acceleration of the origin) - g, w, al = angular velocity, acceleration:
          f = m a + al x h + w x (w x h),   n = I al + w x (I w) + h x a,   h = m c;  tau = -(Jv^T R f + Jw^T R n).
        """
        args = [as_states(k, v, self.n) for k, v in (("q", q), ("dq", dq), ("ddq", ddq))]
        return self._each(lambda *x: self._body_regressor_one(*x, gravity), *args)

    def _body_regressor_one(self, q, dq, ddq, gravity=True):
        m, d = self.model, self.data
        self._kin(q, dq)
        mujoco.mj_comVel(m, d)
        d.qacc[:] = ddq
        mujoco.mj_rnePostConstraint(m, d)             # body accelerations (with -g at the world body)
        vel, acc = np.empty(6), np.empty(6)
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_SITE, self.site, vel, 1)      # [w; v] ee frame
        mujoco.mj_objectAcceleration(m, d, mujoco.mjtObj.mjOBJ_SITE, self.site, acc, 1)  # [al; a - g]
        J, R = self._jac(), d.site_xmat[self.site].reshape(3, 3)
        w, al, a = vel[:3], acc[:3], acc[3:] if gravity else acc[3:] + R.T @ self.g
        A = np.zeros((6, 10))                         # [f; n] = A pi
        A[:3, 0] = a
        A[:3, 1:4] = skew(al) + skew(w) @ skew(w)
        A[3:, 1:4] = -skew(a)
        A[3:, 4:] = _inertia_times(al) + skew(w) @ _inertia_times(w)
        return -(J[:3].T @ R @ A[:3] + J[3:].T @ R @ A[3:])


def _inertia_times(v):
    """L(v) (3, 6) with I v = L(v) (Ixx, Ixy, Iyy, Ixz, Iyz, Izz)."""
    x, y, z = v
    return np.array([[x, y, 0, z, 0, 0], [0, x, y, 0, z, 0], [0, 0, 0, x, y, z]], dtype=float)


def _axis_rotation(a, angle):
    """Rodrigues: rotation matrices (T, 3, 3) about the unit axis a (3,) by angle (T,)."""
    a = np.asarray(a, dtype=float) / np.linalg.norm(a)
    K = skew(a)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)
