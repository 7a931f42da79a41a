"""What tau_ext holds besides the payload (the likelihood's error model, Sec. 4.2's sigma_lik made explicit): per
joint, a constant error over a 200 ms window whose size depends on what the window is referred to, on top of the
noise that averages down (vi.noise_from_window). Calibrated from a robot's own rest log (diagnosis.calibrate)."""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass

import numpy as np

import checks

N = 7

# An uncalibrated Panda at rest: tau_ext is not zero with nothing attached, "a pose-dependent offset of a few tenths
# of a Nm, up to about 1 Nm on J1-J4" (Franka's answer on tau_ext at rest, panda_facts.md); we take 0.5 Nm on J1-J4
# and 0.2 Nm on the wrist joints (the datasheet's 0.15 Nm relative accuracy plus the smaller wrist loads).
PANDA_ABSOLUTE = (0.5, 0.5, 0.5, 0.5, 0.2, 0.2, 0.2)
# A window referred to the level just before a change at the same pose: the robot's model error cancels; what is
# left is the sensor's drift between the two, 5 mNm on the realistic simulated plant (`python sim.py calibration`).
SIM_REFERRED = 0.005
# The robot model's gravity torque is off by a share of itself: link masses +-5-10 % on a real Panda (panda_facts.md,
# "a realistic gap"); we take the low end, 5 % of the gravity torque the calibration poses did not reach.
GRAVITY_SHARE = 0.05


@dataclass(frozen=True)
class ErrorModel:
    """The constant part over a window of what tau_ext holds besides the payload, per joint (n,) [Nm]:
    tau_ext = Y(q) phi + offset + b + e, with b ~ N(0, absolute^2) for a window taken as it is (absolute: the robot
    model's pose-dependent error, a sensor offset that drifts) and b ~ N(0, referred^2) for a window less the level
    before the change at the same pose (what is left: drift, a flexible load's slow vibration). offset: the mean of
    the model's error over the calibration log's poses, subtracted from absolute windows (zeros: uncalibrated)."""
    absolute: tuple = PANDA_ABSOLUTE
    referred: tuple = (SIM_REFERRED,) * N
    offset: tuple = (0.0,) * N
    source: str = "uncalibrated Panda (panda_facts.md)"
    correlation: tuple | None = None   # (n, n) of the absolute error across joints (None: independent joints)
    gravity_range: tuple | None = None  # (2, n) lowest, highest gravity torque G_j(q) [Nm] over the calibration poses
    gravity_share: float = GRAVITY_SHARE   # std of the model's error per Nm of G_j beyond that range
    drift: tuple | None = None   # (n,) [Nm] what a window referred to a baseline window keeps besides the two
                                 #   windows' own slow parts (vi.level_variance); None: referred
    links: tuple | None = None   # (L,) names of the links whose inertial errors dpi (4 L,), per link (m, m cx, m cy,
                                 #   m cz) [kg, kg m], the absolute error holds (pose_error_at); None: the
                                 #   pose-dependent error is absolute and correlation
    link_cov: tuple | None = None    # (n + 4 L, n + 4 L) the covariance of (c, dpi), c the error the offset leaves

    def __post_init__(self):
        n = None
        for name in ("absolute", "referred", "offset"):
            v = getattr(self, name)
            a = checks.real_array(v)                          # bool, complex, text refused, not cast
            if a is None or a.ndim != 1 or a.size < 1 or (n is not None and a.size != n) or not np.all(np.isfinite(a)):
                want = "one finite number per joint" if n is None else f"{n} finite numbers (one per joint, as absolute)"
                raise ValueError(f"error_model.{name}: expected {want} [Nm], found {v!r:.80}")
            n = a.size
            if name != "offset" and not np.all((a > 0) & (a <= 20.0)):
                raise ValueError(f"error_model.{name}: expected stds in (0, 20] Nm (a torque sensor's error, not a "
                                 f"load), found {a.tolist()}")
            if name == "offset" and np.abs(a).max() > 20.0:
                raise ValueError(f"error_model.offset: expected offsets within 20 Nm, found {a.tolist()}")
            object.__setattr__(self, name, tuple(float(x) for x in a))
        if self.correlation is not None:
            R = checks.real_array(self.correlation)
            if R is None or R.shape != (n, n) or not np.all(np.isfinite(R)) or not np.allclose(R, R.T) or \
                    not np.allclose(np.diag(R), 1.0) or np.linalg.eigvalsh(R)[0] <= 1e-9:
                raise ValueError(f"error_model.correlation: expected a ({n}, {n}) positive definite correlation "
                                 f"matrix (symmetric, unit diagonal), found {self.correlation!r:.80}")
            object.__setattr__(self, "correlation", tuple(tuple(float(x) for x in row) for row in R))
        if self.gravity_range is not None:
            G = checks.real_array(self.gravity_range)
            if G is None or G.shape != (2, n) or not np.all(np.isfinite(G)) or np.any(G[0] > G[1]):
                raise ValueError(f"error_model.gravity_range: expected (2, {n}) finite lowest and highest gravity "
                                 f"torques (lowest <= highest) [Nm], found {self.gravity_range!r:.80}")
            object.__setattr__(self, "gravity_range", tuple(tuple(float(x) for x in row) for row in G))
        if self.drift is not None:
            a = checks.real_array(self.drift)
            if a is None or a.shape != (n,) or not np.all(np.isfinite(a)) or not np.all((a > 0) & (a <= 20.0)):
                raise ValueError(f"error_model.drift: expected {n} stds in (0, 20] Nm, found {self.drift!r:.80}")
            object.__setattr__(self, "drift", tuple(float(x) for x in a))
        if self.links is not None:
            self._check_links(n)
        object.__setattr__(self, "gravity_share", checks.number("error_model.gravity_share", self.gravity_share,
                                                                "[0, 1]", "(Nm per Nm of gravity torque)"))
        if not isinstance(self.source, str):
            raise ValueError(f"error_model.source: expected a string, found {self.source!r}")

    @property
    def absolute_cov(self):
        """What an absolute window's constant error is, for vi.precompute's bias_std: (n,) stds of independent
        joints, or the (n, n) covariance diag(absolute) correlation diag(absolute)."""
        a = np.asarray(self.absolute)
        return a if self.correlation is None else a[:, None] * np.asarray(self.correlation) * a[None, :]

    def absolute_cov_at(self, gravity=None):
        """absolute_cov at a pose whose gravity torque is G (n,) [Nm]: beyond the calibration poses' range of G_j
        the model's error is not measured; it grows there by gravity_share per Nm of G_j outside the range, an
        independent part per joint: C + diag((gravity_share d)^2), d_j = max(lo_j - G_j, G_j - hi_j, 0).
        Stds (n,) stay stds (n,); None or no range: absolute_cov."""
        C = self.absolute_cov
        if gravity is None or self.gravity_range is None:
            return C
        lo, hi = np.asarray(self.gravity_range)
        g = np.asarray(gravity, dtype=float)
        extra = (self.gravity_share * np.maximum(np.maximum(lo - g, g - hi), 0.0)) ** 2      # (n,)
        return np.sqrt(C**2 + extra) if C.ndim == 1 else C + np.diag(extra)

    def _check_links(self, n):
        names = self.links
        if not isinstance(names, (tuple, list)) or not names or not all(isinstance(x, str) for x in names):
            raise ValueError(f"error_model.links: expected link (body) names, found {names!r:.80}")
        k = 4 * len(names)
        S = checks.real_array(self.link_cov)
        if S is None or S.shape != (n + k, n + k) or not np.all(np.isfinite(S)) or not np.allclose(S, S.T) or \
                np.linalg.eigvalsh(S)[0] < -1e-9 * max(np.abs(S).max(), 1e-300):
            raise ValueError(f"error_model.link_cov: expected a ({n + k}, {n + k}) covariance (symmetric, positive "
                             f"semidefinite), found {self.link_cov!r:.80}")
        object.__setattr__(self, "links", tuple(names))
        object.__setattr__(self, "link_cov", tuple(tuple(float(x) for x in row) for row in S))

    def pose_error_at(self, A):
        """(mean (n,), covariance (n, n)) [Nm, Nm^2] of an absolute window's constant error at a pose whose links'
        gravity regressor is A (n, 4 L) (dynamics.Robot.link_gravity_regressor of self.links): b = offset + H (c, dpi)
        + u with H = [I, A], so mean offset and covariance H link_cov H^T + diag(absolute^2), u the per-joint part
        no link error explains. The links' errors act through the robot's own gravity regressor: the model carries
        to a pose the calibration has not seen as far as the link model is right."""
        H = np.hstack([np.eye(len(self.offset)), np.asarray(A, dtype=float)])
        return np.asarray(self.offset), H @ np.asarray(self.link_cov) @ H.T + np.diag(np.square(self.absolute))

    def save(self, path) -> None:
        """Write the model as JSON (rme.py calibrate --save)."""
        with open(path, "w") as f:
            json.dump(dict(kind="rme error model", **asdict(self)), f, indent=1)

    @classmethod
    def load(cls, path) -> "ErrorModel":
        """Read a model written by save; ValueError naming what is wrong."""
        if not os.path.isfile(os.fspath(path)):
            raise ValueError(f"error_model: expected a calibration file (.json), found no file at {path!r}")
        try:
            with open(path, encoding="utf-8-sig") as f:
                data = json.load(f)
        except (OSError, ValueError) as err:
            raise ValueError(f"error_model: could not read {path!r} as JSON: {err}") from None
        if not isinstance(data, dict) or data.get("kind") != "rme error model":
            raise ValueError(f"error_model: expected a file written by `rme.py calibrate --save`, found {path!r}")
        missing = {"absolute", "referred", "offset"} - set(data)
        if missing:
            raise ValueError(f"error_model: {path!r} lacks {sorted(missing)}")
        return cls(data["absolute"], data["referred"], data["offset"], str(data.get("source", path)),
                   data.get("correlation"), data.get("gravity_range"), data.get("gravity_share", GRAVITY_SHARE),
                   data.get("drift"), data.get("links"), data.get("link_cov"))


def as_error_model(x, n: int = N) -> ErrorModel:
    """An ErrorModel from an ErrorModel, a path to its JSON, or None: the uncalibrated Panda (n = 7), or for another
    arm of n joints its big joints' 0.5 Nm on every joint (referred: the simulator's)."""
    if x is None:
        return ErrorModel() if n == N else ErrorModel((PANDA_ABSOLUTE[0],) * n, (SIM_REFERRED,) * n, (0.0,) * n,
                                                      source=f"uncalibrated arm of {n} joints")
    if isinstance(x, ErrorModel):
        return x
    if isinstance(x, (str, os.PathLike)):
        return ErrorModel.load(x)
    raise ValueError(f"calibration: expected an ErrorModel, a path to its JSON or None, found {type(x).__name__}")
