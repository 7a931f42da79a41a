"""The robot's error model (error_model.ErrorModel) from its own rest log: what tau_ext holds besides the payload,
per joint, in an absolute window and in one referred to the level before. `python rme.py calibrate LOG [LOG ...]
[--load none|fit] [--pose-model offset|links] --save robot.json [--json]`."""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass, replace

import numpy as np

import checks
import vi
from dynamics import Robot, theta_of
from error_model import ErrorModel
from diagnosis.logs import load_log


@dataclass(frozen=True)
class RestConfig:
    length: int = 200           # samples of a window: RME's 200 ms at 1 kHz (Sec. 4)
    speed: float = 0.01         # rad/s: every |dq| below this in every sample of the window (RMESettings.rest_speed)
    pose: float = 0.05          # rad: windows whose mean poses are this close on every joint count as one pose
    ridge: float = 1e-6         # relative ridge of the least-squares payload (rz is not seen at a level pose)
    separable: float = 0.05     # ours: the load and the offsets are fitted together when the fitted mass's standard
                                #   error is at most this share of it (else the poses cannot tell them apart)


def rest_windows(log, config: RestConfig = RestConfig()):
    """(start, stop) row pairs of windows of `length` samples tiled in each run of rest (every |dq| < speed), and
    for each the index of the window before it in the same run (-1 for a run's first): a referred pair."""
    still = np.abs(log.dq).max(axis=1) < config.speed
    edges = np.flatnonzero(np.diff(np.r_[0, still.astype(int), 0]))
    out, before = [], []
    for a, b in zip(edges[::2], edges[1::2]):
        starts = range(a, b - config.length + 1, config.length)
        before += [len(out) + i - 1 if i else -1 for i in range(len(starts))]
        out += [(k, k + config.length) for k in starts]
    return out, np.array(before, dtype=int)


@dataclass
class RestData:
    """The rest windows of one or more logs, as means: q (W, n), tau (W, n) [Nm], Y (W, n, 4) the mean payload
    regressor; before (W,) the index of the window before in the same rest run (-1: none); the windows' rows for
    their full samples: log index, start, stop (W, 3); gravity (W, n) [Nm] the robot model's G(q) at the mean pose,
    level (W, n) [Nm^2] what each window's mean holds of its own slow part and noise (vi.level_variance) (None: not
    known)."""
    q: np.ndarray
    tau: np.ndarray
    Y: np.ndarray
    before: np.ndarray
    rows: np.ndarray
    logs: list
    gravity: np.ndarray | None = None
    level: np.ndarray | None = None

    def subset(self, keep) -> "RestData":
        """The windows where keep (W,) bool is True; a window whose window before was dropped gets -1 there."""
        keep = np.asarray(keep, dtype=bool)
        new = np.cumsum(keep) - 1                                    # (W,) index among the kept windows
        before = np.where((self.before >= 0) & keep[np.maximum(self.before, 0)], new[np.maximum(self.before, 0)], -1)
        return RestData(self.q[keep], self.tau[keep], self.Y[keep], before[keep], self.rows[keep], self.logs,
                        *(None if x is None else x[keep] for x in (self.gravity, self.level)))

    def pose_labels(self, tol=RestConfig.pose) -> np.ndarray:
        """(W,) the pose of each window: greedy clusters within tol rad on every joint, numbered from 0."""
        centres, labels = [], []
        for q in self.q:
            k = next((i for i, c in enumerate(centres) if np.abs(q - c).max() < tol), len(centres))
            centres += [q] if k == len(centres) else []
            labels.append(k)
        return np.array(labels, dtype=int)

    def poses(self, tol=RestConfig.pose) -> int:
        """How many distinct poses the windows hold (pose_labels)."""
        return int(self.pose_labels(tol).max()) + 1 if len(self.q) else 0


def rest_data(logs, robot: Robot, config: RestConfig = RestConfig()) -> RestData:
    """RestData of the loaded logs (diagnosis.logs.Log, tau_ext in the paper's sign)."""
    q, tau, Y, before, rows, gravity, level = [], [], [], [], [], [], []
    for i, log in enumerate(logs):
        if log.tau_ext is None:
            raise ValueError(f"logs[{i}]: expected tau_ext (or tau_J and a model), found none in {log.info.get('source')}")
        wins, prev = rest_windows(log, config)
        before += [p + len(q) if p >= 0 else -1 for p in prev]
        for a, b in wins:
            q.append(log.q[a:b].mean(axis=0))
            tau.append(log.tau_ext[a:b].mean(axis=0))
            Y.append(robot.payload_regressor(log.q[a:b]).mean(axis=0))
            gravity.append(robot.gravity(q[-1]))
            level.append(vi.level_variance(log.tau_ext[a:b]))
            rows.append((i, a, b))
    n = robot.n
    return RestData(np.reshape(q, (-1, n)), np.reshape(tau, (-1, n)), np.reshape(Y, (-1, n, 4)),
                    np.array(before, dtype=int), np.reshape(rows, (-1, 3)).astype(int), list(logs),
                    np.reshape(gravity, (-1, n)), np.reshape(level, (-1, n)))


def pooled_payload(data: RestData, ridge=RestConfig.ridge) -> np.ndarray:
    """phi (4,) by plain least squares over every window's means: sum_w |tau_w - Y_w phi|^2, a tiny ridge."""
    G = np.einsum("wjp,wjq->pq", data.Y, data.Y)
    return np.linalg.solve(G + ridge * np.trace(G) * np.eye(4), np.einsum("wjp,wj->p", data.Y, data.tau))


def payload_and_offset(data: RestData, config: RestConfig = RestConfig()) -> tuple[np.ndarray, bool, float]:
    """(phi (4,), joint, mass std [kg]) of tau_w = Y_w phi + c, phi and the offsets c (n,) fitted together by least
    squares over the windows, when the poses separate them: the fitted mass's standard error (the residual's
    variance, the windows of a pose counted as one sample) at most config.separable of the mass. Else the load is
    fitted alone (pooled_payload; joint False): the offsets it leaves are what the poses cannot tell from it."""
    W, n = data.tau.shape
    D = np.concatenate([data.Y, np.broadcast_to(np.eye(n), (W, n, n))], axis=2).reshape(W * n, 4 + n)
    G = D.T @ D
    x = np.linalg.solve(G + config.ridge * np.trace(G[:4, :4]) * np.diag(np.r_[np.ones(4), np.zeros(n)]),
                        D.T @ data.tau.reshape(-1))
    res = data.tau.reshape(-1) - D @ x
    var = res @ res / max(W * n - 4 - n, 1) * W / data.poses(config.pose)
    std = float(np.sqrt(max(np.linalg.pinv(G)[0, 0] * var, 0.0)))
    if std > config.separable * max(abs(x[0]), 0.1):                 # (a light load: judged as 0.1 kg)
        return pooled_payload(data, config.ridge), False, std
    return x[:4], True, std


def gravity_range(data: RestData, labels) -> tuple | None:
    """((n,), (n,)) the lowest and highest of each joint's gravity torque G_j(q) over the poses (each pose's mean
    over its windows; labels (W,) from pose_labels), None when data.gravity is not known."""
    if data.gravity is None:
        return None
    gp = np.array([data.gravity[labels == i].mean(axis=0) for i in range(labels.max() + 1)])   # (P, n)
    return tuple(gp.min(axis=0)), tuple(gp.max(axis=0))


def consistent_offset(model: ErrorModel, rp, Yp, phi, Cs=None) -> tuple[ErrorModel, np.ndarray]:
    """(model with its offset moved, the move (n,) [Nm]) so that the model reads its own load at its own poses: the
    mass that generalised least squares gives from a pose's mean torque less the offset (weights: the absolute
    error's covariance C, as RME weighs an absolute window), averaged over the poses, is the calibrated load's mass.
    rp (P, n) the poses' mean residuals, Yp (P, n, 4) their mean regressors, phi (4,) the calibrated load.
    The offset alone, the mean of rp, is no such offset where the poses cannot tell it from the load: subtracting
    it moves each pose's mass by what the offset holds of that pose's load torque. The move is the least in C's
    metric (the error the poses leave, not a new error): delta = C k e / (k^T C k), with k (n,) the averaged mass
    row of the poses' estimators and e the mass they give less phi's. Only the mass: a CoM is seen at some poses.
    What the estimator adds to the data's reading (its prior, the mean-field posterior) is its own, not the error
    model's: docs/real_logs.md measures it. Cs: each pose's own C (P of (n, n); a pose-dependent model), C their
    mean for the move."""
    C = model.absolute_cov if model.correlation is not None else np.diag(np.square(model.absolute))
    Cs = [C] * len(Yp) if Cs is None else list(Cs)
    C = np.mean(Cs, axis=0)
    off, n = np.asarray(model.offset, dtype=float), len(model.offset)
    K = []
    for Y, Cp in zip(Yp, Cs):                                      # (n, 4), (n, n) each
        S = Y.T @ np.linalg.solve(Cp, np.eye(n))                   # (4, n) Y^T C^-1
        G = S @ Y
        K.append(np.linalg.solve(G + 1e-6 * np.trace(G) * np.eye(4), S)[0])   # the mass row; ridge: rz unseen
    k = np.mean(K, axis=0)
    e = float(np.mean([Ki @ (r + Y @ phi - off) for Ki, r, Y in zip(K, rp, Yp)]) - phi[0])
    delta = C @ k * e / max(float(k @ C @ k), 1e-300)
    return replace(model, offset=tuple(off + delta)), delta


# The robot model's link inertials against a real Panda's: masses +-5-10 %, CoM shifts of 5-20 mm (panda_facts.md, "a
# realistic gap"). They set the prior's shape over the links' errors; its scale is fitted on the calibration poses.
LINK_MASS_SHARE = 0.10
LINK_COM_SHIFT = 0.02       # m


def link_prior(robot: Robot, bodies) -> np.ndarray:
    """(4 L,) stds of the links' (m, m cx, m cy, m cz) errors before any log: d(m c) = dm c + m dc, the mass off by
    LINK_MASS_SHARE of itself and the CoM by LINK_COM_SHIFT per axis, independent."""
    pi = robot.link_parameters(bodies).reshape(-1, 4)            # (L, 4)
    m = pi[:, :1]
    mc = np.sqrt((LINK_MASS_SHARE * pi[:, 1:]) ** 2 + (m * LINK_COM_SHIFT) ** 2)
    return np.hstack([LINK_MASS_SHARE * m, mc]).ravel()


def _reml(rp, Ap, prior, log_s, log_u):
    """-log of the restricted likelihood of the poses' mean residuals rp (P, n) under rp_p = c + A_p dpi + u_p, c
    flat, dpi ~ N(0, (e^log_s prior)^2), u_p ~ N(0, diag(e^(2 log_u))) (Patterson and Thompson's REML: the
    offsets' n degrees of freedom taken out). K = D + B B^T, D the u's, B = A diag(e^log_s prior), by Woodbury:
    K^-1 = D^-1 - D^-1 B M^-1 B^T D^-1 and log|K| = log|D| + log|M|, M = I + B^T D^-1 B (k, k)."""
    P, n = rp.shape
    B = Ap.reshape(P * n, -1) * (np.exp(log_s) * prior)            # (P n, k)
    d = np.tile(np.exp(2 * log_u), P)                              # (P n,) the diagonal of D
    M = np.eye(B.shape[1]) + B.T @ (B / d[:, None])
    L = np.linalg.cholesky(M)
    def Ki(V):                                                     # K^-1 V, V (P n, ...)
        DV = V / (d if V.ndim == 1 else d[:, None])
        W = np.linalg.solve(L.T, np.linalg.solve(L, B.T @ DV))
        return DV - (B @ W) / (d if V.ndim == 1 else d[:, None])
    X = np.tile(np.eye(n), (P, 1))                                 # (P n, n)
    F = X.T @ Ki(X)
    res = rp.ravel() - X @ np.linalg.solve(F, X.T @ Ki(rp.ravel()))
    logdet = np.log(d).sum() + 2 * np.log(np.diag(L)).sum()
    return 0.5 * (logdet + np.linalg.slogdet(F)[1] + res @ Ki(res))


def link_errors(rp, Ap, prior, floor=0.001):
    """(scale, u (n,)) of the pose-dependent error as links' inertial errors: rp_p = c + A_p dpi + u_p over the P
    poses (rp (P, n) mean residuals, Ap (P, n, k) the links' gravity regressors, dpi ~ N(0, (scale prior)^2),
    u_p ~ N(0, diag(u^2))), scale and u [Nm] (at least floor) by REML (_reml)."""
    from scipy.optimize import minimize
    n = rp.shape[1]
    x0 = np.r_[0.0, np.log(np.maximum(rp.std(axis=0), 0.01))]
    bounds = [(np.log(1e-3), np.log(30.0))] + [(np.log(floor), np.log(20.0))] * n
    fit = minimize(lambda x: _reml(rp, Ap, prior, x[0], x[1:]), x0, method="L-BFGS-B", bounds=bounds)
    return float(np.exp(fit.x[0])), np.exp(fit.x[1:])


def links_covariance(Ap, prior, scale, u) -> np.ndarray:
    """(n + k, n + k) covariance of (c, dpi), c the offset's error less the poses' mean link error Abar dpi: the
    error at a pose q about the offset (the poses' mean residual), c + A(q) dpi, then has covariance
    u^2 / P + (A - Abar) S (A - Abar)^T, S = diag(scale prior)^2, Abar (n, k) the poses' mean regressor Ap (P, n, k).
    dpi keeps its prior: a few poses cannot tell 4 L link parameters apart (docs/real_logs.md measures the
    posterior's extrapolation against this)."""
    Ab = Ap.mean(axis=0)
    S = np.diag((scale * prior) ** 2)
    V = np.diag(u**2) / len(Ap)
    return np.block([[V + Ab @ S @ Ab.T, -Ab @ S], [-S @ Ab.T, S]])


def referred_drift(data: RestData, r) -> np.ndarray | None:
    """(n,) [Nm] what a window referred to the window before it keeps besides the two windows' own slow parts and
    noise: sqrt(max(mean over the pairs of (r_w - r_b)^2 - level_w - level_b, 0)), r (W, n) the windows' residuals;
    None without data.level or pairs."""
    pairs = np.flatnonzero(data.before >= 0)
    if data.level is None or not len(pairs):
        return None
    b = data.before[pairs]
    excess = (r[pairs] - r[b]) ** 2 - data.level[pairs] - data.level[b]      # (pairs, n)
    return np.sqrt(np.maximum(excess.mean(axis=0), 0.0))


def calibrate(data: RestData, load: str = "none", pose_model: str = "offset", robot: Robot | None = None
              ) -> tuple[ErrorModel, dict]:
    """The error model of the robot in `data` (RestData) and a report. load "none": nothing was attached (phi = 0);
    "fit": one unchanged load, fitted with the model (pooled_payload): the part of the robot's error that looks
    like a payload is then taken into the load, and cannot be calibrated. Per joint, with r_w = tau_w - Y_w phi:
    r_p its mean over the windows of pose p (each pose counts once); offset = mean r_p; absolute = the RMS of r_p
    about it over the P poses, times sqrt(n P / (n P - k)) for the k values fitted (n offsets, 4 more with a load);
    correlation: that of r_p across joints, shrunk to independence by n / (n + P); referred = RMS of r_w - r_before over the pairs of consecutive windows of
    one rest run (what a window referred to the level just before it still holds: drift, a load's vibration), and
    drift the part of it beyond the two windows' own slow parts (referred_drift: for a baseline given as a window);
    gravity_range: the lowest and highest of each joint's G_j(q) over the poses (data.gravity), beyond which the
    absolute error is not measured (ErrorModel.absolute_cov_at). With load "fit", the offset is then moved the least
    that makes the model read its own load's mass at its own poses (consistent_offset; report: offset_shift).
    pose_model "links": the pose-dependent error is instead the robot's links' inertial errors through their gravity
    regressor (robot's, default the Panda; link_errors, links_covariance), absolute the per-joint remainder, no
    correlation and no gravity range (the links' model carries to new poses); the offset is moved as above."""
    if load not in ("none", "fit"):
        raise ValueError(f"load: expected 'none' or 'fit', found {load!r}")
    if pose_model not in ("offset", "links"):
        raise ValueError(f"pose_model: expected 'offset' or 'links', found {pose_model!r}")
    W, n = data.tau.shape
    P = data.poses()
    k = n + (4 if load == "fit" else 0)
    if W < 2 or n * P <= k:
        raise ValueError(f"logs: expected rest windows at more than {k // n} pose(s) to calibrate with load={load!r}, "
                         f"found {W} windows at {P} pose(s)")
    phi, joint, mass_std = payload_and_offset(data) if load == "fit" else (np.zeros(4), True, 0.0)
    r = data.tau - data.Y @ phi                                   # (W, n)
    labels = data.pose_labels()
    rp = np.array([r[labels == i].mean(axis=0) for i in range(P)])   # (P, n): each pose once, however long it rested
    offset = rp.mean(axis=0)
    absolute = np.sqrt(np.mean((rp - offset) ** 2, axis=0) * n * P / (n * P - k)) if P > 1 else np.zeros(n)
    pairs = data.before >= 0
    referred = np.sqrt(np.mean((r[pairs] - r[data.before[pairs]]) ** 2, axis=0)) if pairs.any() else None
    notes = []
    if referred is None:
        notes.append("no rest run holds two windows: the referred error is left at the simulator's value")
        referred = np.asarray(ErrorModel().referred)
    if load == "fit" and not joint:
        notes.append(f"the poses cannot tell the offsets from the load (fitted together, its mass would have a "
                     f"standard error of {mass_std:.3f} kg): the load was fitted alone, and the part of the robot's "
                     f"error that looks like a payload went into it")
    if P < 3:
        notes.append(f"only {P} pose(s): the absolute error's spread over poses is barely measured")
    floor = 0.001                                               # Nm: below the sensor's 0.005 Nm quiescent noise
    absolute = np.maximum(absolute, floor)
    corr = np.corrcoef(rp.T) if P > 2 else np.eye(n)            # the error's correlation across joints over the
    lam = n / (n + P)                                            # poses, shrunk to the identity as few poses back it
                                                                 # (ours: n / (n + P), half at P = n)
    corr = (1 - lam) * np.nan_to_num(corr) + lam * np.eye(n)
    np.fill_diagonal(corr, 1.0)
    model = ErrorModel(tuple(absolute), tuple(np.maximum(referred, floor)), tuple(offset),
                       source=f"calibrated on {len(data.logs)} log(s), {W} rest windows at {P} poses, load {load}",
                       correlation=tuple(map(tuple, corr)),
                       gravity_range=gravity_range(data, labels),
                       drift=None if (drift := referred_drift(data, r)) is None else tuple(np.maximum(drift, floor)))
    shift = np.zeros(n)
    Cs = None
    if pose_model == "links":
        model, Ap, links = _links_model(model, data, labels, rp, robot)
        Cs = [model.pose_error_at(A)[1] for A in Ap]
    if load == "fit":                              # a load fitted beside the offset: the two must agree
        model, shift = consistent_offset(model, rp, np.array([data.Y[labels == i].mean(axis=0) for i in range(P)]),
                                         phi, Cs)
    theta = theta_of(phi) if load == "fit" else np.zeros(4)
    report = dict(windows=int(W), poses=int(P), pairs=int(pairs.sum()), load=load, phi=phi.tolist(),
                  offset_shift=shift.tolist(), load_and_offsets_separated=bool(joint), mass_std=mass_std,
                  theta=np.where(np.isfinite(theta), theta, 0.0).tolist(), absolute=list(model.absolute),
                  referred=list(model.referred), offset=list(model.offset), correlation=[list(x) for x in corr],
                  shrinkage=lam, notes=notes,
                  gravity_range=None if model.gravity_range is None else [list(x) for x in model.gravity_range],
                  gravity_share=model.gravity_share, drift=None if model.drift is None else list(model.drift),
                  pose_model=pose_model, **({"links": links} if pose_model == "links" else {}))
    return model, report


def _links_model(model: ErrorModel, data: RestData, labels, rp, robot: Robot | None):
    """(model with its pose-dependent error as link errors, Ap (P, n, k), report dict) for pose_model "links"."""
    robot = Robot.panda() if robot is None else robot
    bodies = robot.link_bodies()
    Ap = np.array([robot.link_gravity_regressor(data.q[labels == i].mean(axis=0), bodies) for i in range(len(rp))])
    prior = link_prior(robot, bodies)
    scale, u = link_errors(rp, Ap, prior)
    model = replace(model, absolute=tuple(u), offset=tuple(rp.mean(axis=0)), correlation=None, gravity_range=None,
                    links=bodies, link_cov=tuple(map(tuple, links_covariance(Ap, prior, scale, u))))
    return model, Ap, dict(scale=scale, bodies=list(bodies), remainder=list(u), prior=list(prior))


def format_report(rep: dict) -> str:
    f = lambda v: " ".join(f"{x:6.3f}" for x in v)
    lines = [f"error model from {rep['windows']} rest windows of 200 ms at {rep['poses']} poses "
             f"({rep['pairs']} referred pairs), load: {rep['load']}"]
    if rep["load"] == "fit":
        th = rep["theta"]
        lines.append(f"  the load fitted with it: m = {th[0]:.3f} kg, r = ({th[1]:+.3f}, {th[2]:+.3f}, {th[3]:+.3f}) m")
    lines += [f"  joint              " + " ".join(f"{j:>6}" for j in range(1, len(rep['offset']) + 1)),
              f"  offset [Nm]        {f(rep['offset'])}   (subtracted from absolute windows)",
              f"    of it, moved      {f(rep['offset_shift'])}   (so that the model reads its load at its poses)",
              f"  absolute std [Nm]  {f(rep['absolute'])}   (a window taken as it is)",
              f"  referred std [Nm]  {f(rep['referred'])}   (a window less the level just before it)"]
    if rep.get("drift"):
        lines.append(f"  drift std [Nm]     {f(rep['drift'])}   (the same beside the two windows' own swings)")
    if rep.get("links"):
        lk = rep["links"]
        lines.append(f"  links' errors      {lk['scale']:.2f} x ({LINK_MASS_SHARE:.0%} of each mass, "
                     f"{LINK_COM_SHIFT * 1000:.0f} mm of each CoM) on {', '.join(lk['bodies'])};"
                     f" absolute std: the rest")
    if rep.get("gravity_range"):
        lo, hi = rep["gravity_range"]
        lines.append(f"  gravity G(q) [Nm]  " + " ".join(f"{a:+.0f}..{b:+.0f}".rjust(6) for a, b in zip(lo, hi))
                     + f"   (measured within; beyond: {rep['gravity_share']:.0%} of the excess)")
    return "\n".join(lines + [f"  note: {x}" for x in rep["notes"]])


def main(argv=None, prog: str = "rme.py calibrate") -> int:
    p = checks.Parser(prog=prog, description="Calibrate RME's error model from rest windows of your robot's logs "
                      "(libfranka-style CSV or franka.py .npz).")
    p.add_argument("logs", nargs="+", metavar="LOG")
    p.add_argument("--load", choices=("none", "fit"), default="none",
                   help="none: nothing attached; fit: one unchanged load, fitted with the model")
    p.add_argument("--pose-model", choices=("offset", "links"), default="offset",
                   help="offset: the pose-dependent error as an offset and a covariance over the poses; links: as the "
                        "robot's links' inertial errors through their gravity torque (carries to new poses)")
    p.add_argument("--save", metavar="FILE", help="write the model as JSON (RME(calibration=FILE))")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    args = p.parse_args(argv)
    try:
        if args.save:
            checks.output_file("--save", args.save)            # before any work
        robot = Robot.panda()
        data = rest_data([load_log(x) for x in args.logs], robot)
        model, rep = calibrate(data, args.load, args.pose_model, robot)
    except ValueError as err:
        print(f"{prog}: {err}", file=sys.stderr)
        return 2
    if args.save:
        try:
            model.save(args.save)
        except OSError as err:
            print(f"{prog}: --save: could not write {args.save!r}: {err}", file=sys.stderr)
            return 2
        rep["saved"] = args.save
    print(json.dumps(rep) if args.json else format_report(rep) + (f"\nsaved to {args.save}" if args.save else ""))
    return 0
