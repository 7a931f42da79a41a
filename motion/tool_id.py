"""The tool's mass, CoM and inertia from a motion: tau_ext = Y(q, dq, ddq) pi + per-joint friction, rotor inertia and
offset (partialled out, Frisch-Waugh), pi held physical (motion.inertia.fit_inertia, Wensing et al. 2017); intervals
by the fit's covariance carried to the flange frame; each parameter observed or not."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import savgol_filter

from dynamics import Robot
from motion.inertia import FitInfo, FitSettings, fit_inertia
from motion.tool_forms import Tool, params_of_tool, tool_of_params

NAMES = ("mass", "com_x", "com_y", "com_z", "Ixx", "Iyy", "Izz", "Ixy", "Ixz", "Iyz")   # the reported parameters (F)


@dataclass(frozen=True)
class ToolFitSettings:
    every: int = 10                 # samples between rows (the log's 77-sample filters, robot.identify.LOG: neighbours
    #                                overlap)
    edge: int = 50                  # samples left out at each end (the filters' edges, half a window and more)
    friction_widths: tuple = (0.02, 0.1)   # rad/s: tanh(dq / w) per joint beside dq, ddq and 1 (Gaz et al. 2019's
    #                                sigmoid friction has widths 2 / p2 = 0.1-0.4 rad/s; the narrower one for stiction)
    resolution: tuple = (0.01, 0.003, 0.15)   # what a parameter must be known to, at 2 std, to count as observed:
    #                                kg (or 1 % of the mass if more), m per CoM axis, share of the inertia's diagonal
    #                                (the precision Desk's fields are worth: the benchmark's targets)
    reference_tolerance: float = 0.05   # rad: rms q difference over the motion for a reference to be the same
    #                                motion (a 1 kg tool sags joint 6 by 0.025 rad rms under its 50 Nm/rad spring)
    hac_lags: int = 30              # rows (0.3 s) over which the residual's correlation is summed in the std
    #                                (the 77-sample filters span 8 rows; the arm's error varies more slowly)
    state_difference: bool = True   # referred: partial out each joint's friction and rotor inertia of the
    #                                difference between the two motions (the tool's weight and inertia make the arm
    #                                track the reference a little differently; the drives' own torques differ with it)
    drive_spread: bool = True       # referred: each std includes how much the result moves when the drives' model of
    #                                the motions' difference loses its rotor-inertia or its friction terms
    #                                (_drive_model_spread; on the benchmark the errors were 1.25-1.5 std rms without
    #                                it, 0.8-1.1 with it, tuning and held-out seeds, docs/tool_identification.md)
    drive_share: float = 0.05       # referred: the drives' model of the motions' difference taken as known to this
    #                                share of its torque, which each row's variance gets beside the residual's
    #                                (_row_scale): rows where that torque dwarfs the noise (franky-sim's lift-back of
    #                                the sagged arm, 0.3-0.8 Nm against 2-5 mNm) count for less; chosen among 0.03-1 on
    #                                the benchmark's seeds 0-9 and franky-sim's two tools (docs/tool_identification.md)
    drift: bool = True              # referred: each joint's sensor offset may differ between the two runs (a Panda's
    #                                torque sensors drift with temperature: 0.05-0.08 Nm between windows minutes
    #                                apart on the beam logs, docs/real_logs.md); a constant per joint is partialled
    #                                out with the drives' terms (the mass then comes from the weight's change over
    #                                the cone's poses, not from its level at the start pose)
    q_columns: tuple = (6,)         # referred: joints (0-based) whose drives' columns of the difference are built
    #                                from q (Savitzky-Golay derivatives over q_window, _from_q): joint 7's. Built from
    #                                the logged dq and ddq they are mostly noise (on the realistic plant joint 7's ddq
    #                                difference carries 0.030 rad/s^2 rms of differentiated dq noise against 0.023-0.027
    #                                of signal), which shrinks their coefficients (errors in the variables) and leaves
    #                                the drives' torque of the difference in Izz: -1.7 % from joint 7's columns, within
    #                                0.04 % from each other joint's (seeds 0-9). From q (a Panda's q carries 2-4e-6 rad
    #                                of noise, dq 0.8-1.5e-3 rad/s: beam logs) ddq's noise is 50 times less. Joints 5
    #                                and 6 keep the logged ones: built from q their columns took Iyy's information
    #                                (Iyy -8.0 %, sd 9.2, against -2.4 %, sd 2.7) (docs/tool_identification.md)
    q_window: float = 0.075         # s: the derivatives' Savitzky-Golay window (order 3), the log's own filter
    #                                (robot.identify.LOG), so the columns pass what the torques pass
    fit: FitSettings = field(default_factory=lambda: FitSettings(prior_std=(5.0, 1.0, 1.0, 1.0), inertia_std=1.0))
    #                                a weak prior: 5 kg, 1 kg m, 1 kg m^2 (the data decide)


@dataclass
class ToolFit:
    """A fit: the tool (flange frame), pi (10,) in the ee frame, value / std / observed per NAMES (std 1-sigma: the
    noise's, the larger of the white-residual one and the one with the residual's correlation over 0.3 s, _sandwich,
    with the drives' model's, drive_std, _drive_model_spread, added in quadrature), the fit's FitInfo, rows used, the
    per-joint residual rms [Nm], and notes (what the data could not tell)."""
    tool: Tool
    pi: np.ndarray
    value: dict
    std: dict
    observed: dict
    info: FitInfo
    rows: int
    residual: np.ndarray
    notes: list
    drive_std: dict = field(default_factory=dict)   # per NAMES the part of std from the drives' model

    def report(self) -> dict:
        return {"parameters": {k: {"value": self.value[k], "std": self.std[k], "interval_2std": [
            self.value[k] - 2 * self.std[k], self.value[k] + 2 * self.std[k]], "observed": self.observed[k],
            "std_of_drive_model": self.drive_std.get(k, 0.0)}
            for k in NAMES}, "status": self.info.status, "rows": self.rows,
            "residual_rms_Nm": np.round(self.residual, 4).tolist(), "notes": self.notes}


def nuisance(dq, ddq, widths) -> np.ndarray:
    """Z (T, n, k): per joint 1, dq, tanh(dq / w) for each width, ddq: offset, viscous and Coulomb-like friction,
    rotor inertia (the torques a joint's own drive adds to tau_ext)."""
    cols = [np.ones_like(dq), dq] + [np.tanh(dq / w) for w in widths] + [ddq]
    return np.stack(cols, axis=2)


def partial_out(Y, tau, Z):
    """Y (T, n, 10), tau (T, n) less their least-squares projection on each joint's own Z (T, n, k) (Frisch-Waugh:
    the pi that fits the residuals is the pi of the joint fit with the nuisance)."""
    Yr, tr = np.empty_like(Y), np.empty_like(tau)
    for j in range(Y.shape[1]):
        Zj = Z[:, j]
        U, s, _ = np.linalg.svd(Zj, full_matrices=False)
        U = U[:, s > 1e-9 * max(s.max(), 1e-300)]           # a joint that never moves: its dq columns are 0
        Yr[:, j] = Y[:, j] - U @ (U.T @ Y[:, j])
        tr[:, j] = tau[:, j] - U @ (U.T @ tau[:, j])
    return Yr, tr


def fit_tool(robot: Robot, q, dq, ddq, tau_ext, reference=None, settings: ToolFitSettings = ToolFitSettings(),
             dt: float = 1e-3, keep=None):
    """The tool from a motion: q, dq, ddq, tau_ext (T, n) (tau_ext in the paper's sign, filtered alike with dq,
    diagnosis.logs.prepare; the tool's whole torque, nothing of it configured). reference: (q, dq, ddq, tau_ext)
    (T', n) of the same motion with the flange empty (row k beside row k): its tau_ext is subtracted, which removes the arm's
    own model error and the sensor's offsets (Khalil, Gautier, Lemoine 2007: loaded minus unloaded), so the tool's
    whole torque is fitted, its weight at every pose included (what gives the mass); without it the joints' friction
    and rotor inertia are partialled out, and the arm's model error of links 5-7 stays in the result (a note says so).
    dt: the samples' period [s] (the q_columns' derivatives). keep (T,) bool: the rows that may be fitted (None:
    all; the derivatives still use every row). Returns a ToolFit."""
    arrays = [np.asarray(a, dtype=float) for a in (q, dq, ddq, tau_ext)]
    n, s = robot.n, settings
    if reference is not None:
        arrays = _referred(arrays, reference, settings.reference_tolerance)
        ddq_ref, dq_ref, q_ref = arrays.pop(), arrays.pop(), arrays.pop()
    if any(a.ndim != 2 or a.shape != arrays[0].shape or a.shape[1] != n for a in arrays):
        raise ValueError(f"q, dq, ddq, tau_ext: expected four (T, {n}) arrays, found {[a.shape for a in arrays]}")
    if not all(np.isfinite(a).all() for a in arrays):
        raise ValueError("q, dq, ddq, tau_ext: expected finite values, found NaN or inf")
    rows = np.arange(s.edge, len(arrays[0]) - s.edge, s.every)
    if keep is not None:
        keep = np.asarray(keep)
        if keep.dtype != bool or keep.shape != (len(arrays[0]),):
            raise ValueError(f"keep: expected a ({len(arrays[0])},) bool array, found {keep.dtype} {keep.shape}")
        rows = rows[keep[rows]]
    if len(rows) < 50:
        raise ValueError(f"q: expected at least {50 * s.every + 2 * s.edge} samples, found {len(arrays[0])}")
    q, dq, ddq, tau = (a[rows] for a in arrays)
    Y = robot.body_regressor(q, dq, ddq)                    # (T, n, 10)
    if reference is None:
        Z, fit_settings = nuisance(dq, ddq, s.friction_widths), s.fit
    else:       # referred: the offsets are the reference's too; what the drives add for the states' difference stays
        Z = nuisance(dq, ddq, s.friction_widths) - nuisance(dq_ref[rows], ddq_ref[rows], s.friction_widths)
        if s.q_columns:
            (v, a), (v_ref, a_ref) = (_from_q(x, dt, s.q_window) for x in (arrays[0], q_ref))
            from_q = nuisance(v[rows], a[rows], s.friction_widths) - nuisance(v_ref[rows], a_ref[rows],
                                                                              s.friction_widths)
            Z[:, list(s.q_columns)] = from_q[:, list(s.q_columns)]
        Z[:, :, 0] = 1.0 if s.drift else 0.0             # the offsets' column (1 - 1 = 0 in the difference)
        Z = Z if s.state_difference else Z[:, :, :1]
        fit_settings = dataclasses.replace(s.fit, offsets=False)
    share = s.drive_share if reference is not None and s.state_difference else 0.0
    pi, info, Yr, tr, Y, tau, Z = _weighted_fit(Y, tau, Z, fit_settings, share)
    tool = tool_of_params(pi)
    value, J = _parameters(pi), _jacobian(pi)
    noise = _noise_variance(J, info, Yr, tr, s)
    spread = reference is not None and s.state_difference and s.drive_spread
    drives = _drive_model_spread(Y, tau, Z, value, fit_settings) if spread else np.zeros(len(NAMES))
    std = np.sqrt(np.maximum(noise, 0.0) + drives ** 2)
    observed = _observed(value, std, s.resolution)
    notes = [f"{k} not observed: the motion leaves it at {value[i]:.4g} +- {2 * std[i]:.2g} (2 std)"
             for i, k in enumerate(NAMES) if not observed[i]]
    if reference is None:
        notes.append("no reference motion with the flange empty: the arm's own model error of links 5-7 (its "
                     "masses and CoMs) is in the result, beyond the intervals")
    if info.status != "ok":
        notes.append(f"the least-squares optimum was not a physical body; the nearest physical one is given "
                     f"({info.status})")
    return ToolFit(tool, pi, dict(zip(NAMES, value.tolist())), dict(zip(NAMES, std.tolist())),
                   dict(zip(NAMES, observed)), info, len(rows), info.residual, notes, dict(zip(NAMES, drives.tolist())))


def _weighted_fit(Y, tau, Z, settings: FitSettings, share: float):
    """_fit, and with share > 0 again on the rows scaled by _row_scale at the first fit's pi (weighted least squares):
    (pi, FitInfo, the partialled Y and tau, the scaled Y, tau, Z)."""
    pi, info, Yr, tr = _fit(Y, tau, Z, settings)
    if share > 0:
        a = _row_scale(Y, tau, Z, pi, share)[..., None]
        Y, tau, Z = Y * a, tau * a[..., 0], Z * a
        pi, info, Yr, tr = _fit(Y, tau, Z, settings)
    return pi, info, Yr, tr, Y, tau, Z


def _row_scale(Y, tau, Z, pi, share: float) -> np.ndarray:
    """(T, n) per row and joint sigma_j / sqrt(sigma_j^2 + (share d_tj)^2): d the drives' torque of the motions'
    difference as fitted at pi (Z's columns but the offset, each joint's least squares on tau - Y pi), sigma_j the rms
    of what is left; a row's weight falls where the result would lean on that model more than on the tool."""
    e = tau - Y @ pi
    scale = np.ones_like(tau)
    for j in range(Y.shape[1]):
        beta = np.linalg.lstsq(Z[:, j], e[:, j], rcond=None)[0]
        d, left = Z[:, j, 1:] @ beta[1:], e[:, j] - Z[:, j] @ beta
        var = np.mean(left ** 2)
        if var > 0.0:
            scale[:, j] = np.sqrt(var / (var + (share * d) ** 2))
    return scale


def _fit(Y, tau, Z, settings: FitSettings):
    """fit_inertia on Y (T, n, 10), tau (T, n) with each joint's Z (T, n, k) partialled out (none if Z is all 0):
    (pi, FitInfo, the partialled Y and tau)."""
    Yr, tr = partial_out(Y, tau, Z) if np.any(Z) else (Y, tau)
    pi, info = fit_inertia(Yr, tr, np.zeros(4), None, settings)
    return pi, info, Yr, tr


def _noise_variance(J, info: FitInfo, Yr, tr, s: ToolFitSettings) -> np.ndarray:
    """(len(NAMES),) the noise's variance of each reported value (J (len(NAMES), 10) their Jacobian in pi): the larger
    of the white residual's (info.cov) and the one with the residual's correlation (_sandwich)."""
    return np.maximum(np.einsum("ki,ij,kj->k", J, info.cov, J),
                      np.einsum("ki,ij,kj->k", J, _sandwich(Yr, tr, info, s), J))


def _drive_model_spread(Y, tau, Z, value, settings: FitSettings) -> np.ndarray:
    """(10,) per NAMES: the rms change of the result when the fit is made without the drives' rotor-inertia column
    (Z[..., -1]) and without their friction columns (Z[..., 1:-1]): how much the result leans on the model of what the
    drives add for the two motions' difference (a torque the tool itself causes, measured through noisy dq and ddq)."""
    keep = [list(range(Z.shape[2] - 1)), [0, Z.shape[2] - 1]]
    moved = [_parameters(_fit(Y, tau, Z[:, :, k], settings)[0]) - value for k in keep]
    return np.sqrt(np.mean(np.square(moved), axis=0))


def _sandwich(Y, tau, info: FitInfo, s: ToolFitSettings) -> np.ndarray:
    """cov (10, 10) of the least-squares pi with the rows' residuals correlated in time (the filters, the arm's slowly
    varying error): G^-1 (sum over lags |k| <= L of (1 - |k| / (L + 1)) Gamma_k) G^-1, Gamma_k = sum_t g_t g_{t-k}^T,
    g_t = sum_j w_j^2 Y_tj^T e_tj (Newey and West 1987), G the weighted normal matrix with the prior."""
    w2 = info.weights ** 2
    e = tau - Y @ info.unconstrained                                   # (T, n)
    g = np.einsum("j,tjk,tj->tk", w2, Y, e)                            # (T, 10) scores
    prior = np.diag(1.0 / np.square([*s.fit.prior_std, *[s.fit.inertia_std] * 6]))
    Ginv = np.linalg.inv(np.einsum("j,tji,tjk->ik", w2, Y, Y) + prior)
    S = g.T @ g
    for k in range(1, s.hac_lags + 1):
        Gk = g[k:].T @ g[:-k]
        S += (1.0 - k / (s.hac_lags + 1)) * (Gk + Gk.T)
    return Ginv @ S @ Ginv


def _referred(arrays, reference, tolerance):
    """arrays with the reference's tau_ext subtracted row by row (both cut to the shorter) and the reference's dq,
    ddq; ValueError when the reference's q is not the same motion (rms difference above tolerance on a joint)."""
    try:
        q_ref, dq_ref, ddq_ref, tau_ref = (np.asarray(a, dtype=float) for a in reference)
    except (TypeError, ValueError):
        raise ValueError("reference: expected (q, dq, ddq, tau_ext) arrays of the motion with the flange empty") \
            from None
    n = arrays[0].shape[1]
    if q_ref.ndim != 2 or q_ref.shape[1] != n or any(a.shape != q_ref.shape for a in (dq_ref, ddq_ref, tau_ref)):
        raise ValueError(f"reference: expected q, dq, ddq, tau_ext of shape (T, {n}), found "
                         f"{[a.shape for a in (q_ref, dq_ref, ddq_ref, tau_ref)]}")
    T = min(len(q_ref), len(arrays[0]))
    gap = np.sqrt(np.mean((arrays[0][:T] - q_ref[:T]) ** 2, axis=0))
    if T < 0.95 * max(len(q_ref), len(arrays[0])) or gap.max() > tolerance:
        raise ValueError(f"reference: expected the same motion (rms q difference <= {tolerance} rad, lengths within "
                         f"5 %), found rms {np.round(gap, 4).tolist()} rad, {len(q_ref)} and {len(arrays[0])} samples")
    q, dq, ddq, tau = (a[:T] for a in arrays)
    return [q, dq, ddq, tau - tau_ref[:T], q_ref[:T], dq_ref[:T], ddq_ref[:T]]


def _from_q(q, dt: float, window: float):
    """(dq, ddq) (T, n) of q (T, n) by Savitzky-Golay derivatives of order 3 over `window` seconds (at least 5
    samples, at most the log)."""
    win = min(max(2 * int(round(window / dt / 2)) + 1, 5), len(q) - (len(q) + 1) % 2)
    return tuple(savgol_filter(q, win, 3, deriv=k, delta=dt, axis=0, mode="interp") for k in (1, 2))


def _parameters(pi) -> np.ndarray:
    """(10,) the NAMES of tool_of_params(pi): mass, com (F), inertia about the CoM (F) diagonal then off-diagonal."""
    t = tool_of_params(pi)
    I = t.inertia
    return np.array([t.mass, *t.com, I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])


def _jacobian(pi, h: float = 1e-7) -> np.ndarray:
    """d _parameters / d pi (10, 10) by central differences (steps scaled to each entry)."""
    J = np.empty((10, 10))
    for i in range(10):
        d = np.zeros(10)
        d[i] = h * max(abs(pi[i]), 1e-3)
        J[:, i] = (_parameters(pi + d) - _parameters(pi - d)) / (2 * d[i])
    return J


def _observed(value, std, resolution) -> list:
    """Each parameter's 2 std within its resolution: mass max(kg, 1 %), CoM m, inertia share of the diagonal's mean
    (off-diagonals) or of its own value (diagonal)."""
    kg, m, share = resolution
    diag = np.abs(value[4:7])
    limit = np.concatenate([[max(kg, 0.01 * abs(value[0]))], [m] * 3, share * np.maximum(diag, 1e-4),
                            [share * max(diag.mean(), 1e-4)] * 3])
    return [bool(2 * s <= lim) for s, lim in zip(std, limit)]


def truth_of(tool: Tool) -> dict:
    """NAMES -> value of a known tool (for benchmarks and tests)."""
    return dict(zip(NAMES, _parameters(params_of_tool(tool)).tolist()))
