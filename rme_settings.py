"""What the pipeline (rme.py) is told: RMESettings, the streaming estimator's settings (rme re-exports it), and
faulty, which tau_ext samples are sensor faults."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import checks
import vi
from changes import ChangeSettings
from detector import MAX_TORQUE, DetectorSettings


@dataclass(frozen=True)
class RMESettings:
    window: int = 200              # samples of the estimation window: 200 ms at 1 kHz (Sec. 4, App. E); at a
                                   #   detection the newest detection_window (below), the level settled over them
    rate: float = 1000.0           # Hz, the control loop (Franka's 1 kHz)
    use_network: bool = True       # prior mean from the network (False: zero prior mean, Table 1's ablation)
    asynchronous: bool = True      # ours: compensation starts once the estimate's own wall time has passed, as if
                                   #   the estimate ran beside the loop (False: applied on the detection sample)
    max_mass: float = 3.0          # kg, Panda's rated payload: the compensation never assumes more
    max_com: float = 0.3           # m, |rx|, |ry|, |rz| of a payload a hand can carry (ours): the payload
                                   #   hypothesis' box (changes.Payloads); an estimate beyond it is not applied
    rest_speed: float = 0.01       # rad/s, every joint slower than this counts as still (dq noise is 1e-3): the
                                   #   level may become the reference, the noise is learned
    max_abs_torque: float = 1e3    # Nm: a sample beyond this, or not finite, is dropped (and counted in `dropped`)
    changes: ChangeSettings = field(default_factory=ChangeSettings)   # what the residual holds (changes.py)
    detector: DetectorSettings | None = None   # None: the model of what changed decides (changes.py); a
                                   #   DetectorSettings: Algorithm 1 as printed fires each estimate instead
                                   #   (detector.py; the paper's, for its reproduction)
    vi: vi.VISettings = field(default_factory=vi.VISettings)

    def __post_init__(self):
        """Every field checked where it is given (checks.py); the upper bounds keep every product with a rate or a
        torque finite and are far beyond any arm: 10 kHz loops, 50 kg payloads (UR30: 30 kg), 1 m CoMs (the Panda
        reaches 0.855 m), torques up to max_abs_torque (<= the detector's MAX_TORQUE)."""
        c = checks
        c.number("settings.max_abs_torque", self.max_abs_torque, f"(0, {MAX_TORQUE:g}]", "Nm")
        c.instance("settings.vi", self.vi, vi.VISettings)
        c.instance("settings.changes", self.changes, ChangeSettings)
        if self.detector is not None:
            c.instance("settings.detector", self.detector, DetectorSettings)
        for name in ("use_network", "asynchronous"):
            c.flag(f"settings.{name}", getattr(self, name))
        c.number("settings.window", self.window, "20..500", "samples")
        c.number("settings.rate", self.rate, "[10, 1e4]", "Hz")
        c.number("settings.max_mass", self.max_mass, "(0, 50]", "kg")
        c.number("settings.max_com", self.max_com, "(0, 1]", "m")
        c.number("settings.rest_speed", self.rest_speed, "(0, 1]", "rad/s")
        if self.detection_window < 20:
            raise ValueError(f"settings.detector.check_windows: expected an earliest check that leaves at least 20 "
                             f"samples after it (the detection's window), found {self.detector.check_windows}")

    @property
    def detection_window(self) -> int:
        """Samples of the window estimated at a detection: the newest 2 changes.short (the level was steady over
        them), at most `window`; with Algorithm 1 (detector), those from its earliest stabilisation check on, which it
        found settled after the change (230, so `window`'s 200 with Alg. 1's own checks)."""
        d = self.detector
        if d is None:
            return min(self.window, 2 * self.changes.short)
        return min(self.window, d.window + 1 - min(w[0] for w in d.check_windows))


def faulty(tau_ext, limit=RMESettings.max_abs_torque) -> bool:
    """Whether a tau_ext sample (n,) is a sensor fault, not a load: not finite, or a joint beyond `limit` [Nm]
    (RME drops it; the robot loop hands its controller the last good sample instead)."""
    return not np.abs(tau_ext).max() <= limit         # (NaN compares False)
